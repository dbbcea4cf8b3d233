"""The command line end to end: simulate → replay → eval, demo, import, and its error paths."""

import json
from pathlib import Path

import numpy as np
import pytest

from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.files.tum import read_tum
from vtolpose.service.cli import COMMANDS, build_parser, main


@pytest.fixture(scope="module")
def book_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("data") / "book"
    assert main(["-q", "simulate", "--scenario", "book", "--duration", "40", "--seed", "2", "--out", str(out), "--no-camera"]) == 0
    return out


def test_every_command_has_help_that_teaches(capsys):
    for name in COMMANDS:
        with pytest.raises(SystemExit) as exit_info:
            build_parser().parse_args([name, "--help"])
        assert exit_info.value.code == 0
        text = capsys.readouterr().out
        assert len(text.splitlines()) > 5, name
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--help"])
    assert "vtolpose demo" in capsys.readouterr().out


def test_the_listing_says_what_each_command_module_says():
    """The top-level help lists the subcommands from cli.COMMANDS without importing them: its lines must be the
    modules' own."""
    import argparse

    full = build_parser()
    sub = next(a for a in full._actions if isinstance(a, argparse._SubParsersAction))
    assert {c.dest: c.help for c in sub._choices_actions} == COMMANDS


def test_top_level_help_imports_no_subcommand_and_nothing_heavy():
    import subprocess
    import sys

    probe = ("import sys, contextlib, io\n"
             "from vtolpose.service.cli import main\n"
             "with contextlib.redirect_stdout(io.StringIO()):\n"
             "    try: main(['--help'])\n"
             "    except SystemExit: pass\n"
             "print(' '.join(sorted(m for m in sys.modules if m.startswith('vtolpose.service.commands.')"
             " or m in ('numpy', 'cv2', 'scipy', 'zenoh', 'pymavlink'))))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout.split()
    assert out == []


HEAVY_MODULES = ("numpy", "cv2", "numba", "zenoh", "pymavlink", "scipy")


def test_every_subcommand_help_imports_nothing_heavy():
    """``vtolpose X --help`` builds X's parser only: the modules its work needs load when it runs."""
    import subprocess
    import sys

    probe = ("import sys, contextlib, io\n"
             "from vtolpose.service.cli import COMMANDS, main\n"
             f"heavy = {HEAVY_MODULES!r}\n"
             "for name in COMMANDS:\n"
             "    with contextlib.redirect_stdout(io.StringIO()):\n"
             "        try: main([name, '--help'])\n"
             "        except SystemExit: pass\n"
             "    print(name, ','.join(sorted(m for m in sys.modules if m.split('.')[0] in heavy)) or '-')\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    loaded = dict(line.split(" ", 1) for line in out.splitlines())
    assert set(loaded) == set(COMMANDS)
    assert {name: modules for name, modules in loaded.items() if modules != "-"} == {}


def test_the_names_the_light_parsers_keep_are_their_modules_own():
    from vtolpose.drivers.files.euroc_import import default_mounting_path
    from vtolpose.drivers.simulator import SCENARIOS
    from vtolpose.service.bench import catalog, runner
    from vtolpose.service.commands import importer, map as map_command, simulate
    from vtolpose.service.mapping.poses import WAIT_KINDS

    assert simulate.SCENARIO_NAMES == tuple(sorted(SCENARIOS))
    assert importer.MOUNTING_NAME == default_mounting_path().name
    assert map_command.WAIT_KINDS == WAIT_KINDS
    assert catalog.SUMMARIES == {name: fn.__doc__.strip().splitlines()[0] for name, fn in runner.BENCHMARKS.items()}
    assert set(catalog.LONG_BENCHMARKS + catalog.GROUPS) <= set(runner.BENCHMARKS)


def test_a_subcommand_line_builds_only_its_own_parser():
    import argparse

    parser = build_parser(["eval"])
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert any(a.dest == "truth" for a in sub.choices["eval"]._actions)
    assert not any(a.dest == "sensors" for a in sub.choices["replay"]._actions)  # the stub: a help line only


def test_simulate_writes_the_same_bytes_for_the_same_seed(book_dir, tmp_path):
    again = tmp_path / "again"
    main(["-q", "simulate", "--scenario", "book", "--duration", "40", "--seed", "2", "--out", str(again), "--no-camera"])
    for rel in ("dataset.yaml", "mav0/imu0/data.csv", "mav0/gps0/data.csv", "mav0/state_groundtruth_estimate0/data.csv"):
        assert (again / rel).read_bytes() == (book_dir / rel).read_bytes(), rel


def test_simulate_can_start_in_flight(book_dir, tmp_path, capsys):
    """--start-in-flight: the scenario's in-flight point (book: 20 s in), or the seconds given."""
    default, given = tmp_path / "default", tmp_path / "given"
    assert main(["-q", "simulate", "--scenario", "book", "--duration", "5", "--seed", "2", "--out", str(default),
                 "--no-camera", "--start-in-flight"]) == 0
    assert main(["-q", "simulate", "--scenario", "book", "--duration", "5", "--seed", "2", "--out", str(given),
                 "--no-camera", "--start-in-flight", "20"]) == 0
    rel = "mav0/state_groundtruth_estimate0/data.csv"
    assert (default / rel).read_bytes() == (given / rel).read_bytes() != (book_dir / rel).read_bytes()
    joined, from_rest = Dataset.open(default), Dataset.open(book_dir)
    np.testing.assert_allclose(joined.truth().p[0], from_rest.truth().p[2000], atol=1e-6)
    assert joined.calibration.initial_heading_rad is None  # nobody states a heading in the air
    with pytest.raises(SystemExit):
        main(["simulate", "--out", str(tmp_path / "x"), "--start-in-flight", "-2"])
    assert "must be a finite number of seconds >= 0" in capsys.readouterr().err


def test_simulate_refuses_to_overwrite_without_force(book_dir, capsys):
    assert main(["simulate", "--scenario", "book", "--duration", "5", "--out", str(book_dir), "--no-camera"]) == 1
    assert "already holds a dataset" in capsys.readouterr().err


def test_replay_writes_trajectory_and_report_then_eval_agrees(book_dir, tmp_path, capsys):
    traj, report_path = tmp_path / "traj.txt", tmp_path / "report.json"
    assert main(["-q", "replay", str(book_dir), "--out", str(traj), "--report", str(report_path), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "position RMSE" in printed and "NEES mean" in printed
    report = json.loads(report_path.read_text())
    for key in ("position_rmse_m", "attitude_rmse_deg", "gps_rmse_m", "nees_mean", "duration_s", "wall_s", "realtime_factor", "sensors"):
        assert key in report, key
    assert report["sensors"]["gps"]["used"] > 300 and "rejected" in report["sensors"]["gps"]
    assert report["position_rmse_m"] < 0.7 * report["gps_rmse_m"]
    t, p, q = read_tum(traj)
    assert len(t) == report["estimates"] and q is not None
    scores_path = tmp_path / "scores.json"
    assert main(["eval", str(traj), "--truth", str(book_dir), "--report", str(scores_path)]) == 0
    scores = json.loads(scores_path.read_text())
    assert scores["position_rmse_m"] == pytest.approx(report["position_rmse_m"], rel=1e-6)
    printed = capsys.readouterr().out
    assert f"position RMSE {scores['position_rmse_m']:.4f} m" in printed
    assert "0000000" not in printed and "{" not in printed  # rounded figures, not raw JSON


def test_replay_variant_and_set_override(book_dir, tmp_path):
    def gate_rejections(*extra: str) -> tuple[str, int]:
        path = tmp_path / "r.json"
        assert main(["-q", "replay", str(book_dir), "--variant", "thesis", *extra, "--report", str(path), "--no-progress"]) == 0
        report = json.loads(path.read_text())
        return report["variant"], report["sensors"]["gps"]["rejected"].get("chi2_gate", 0)

    variant, default_gate = gate_rejections()
    assert variant == "thesis"
    _, narrow_gate = gate_rejections("--set", "estimator.gps.gate_chi2=2.0")
    assert narrow_gate > default_gate + 20  # the override reached the GPS gate


def test_replay_without_gps_is_reported(book_dir, tmp_path):
    report_path = tmp_path / "r.json"
    nogps = tmp_path / "nogps"
    import shutil

    shutil.copytree(book_dir, nogps)
    shutil.rmtree(nogps / "mav0" / "gps0")
    assert main(["-q", "replay", str(nogps), "--report", str(report_path), "--no-progress"]) == 0
    report = json.loads(report_path.read_text())
    assert any("no GPS stream" in note for note in report["notes"])
    assert "gps_rmse_m" not in report


def test_errors_are_messages_not_tracebacks(book_dir, tmp_path, capsys):
    assert main(["replay", str(tmp_path / "missing")]) == 1
    assert "dataset folder not found" in capsys.readouterr().err
    assert main(["replay", str(book_dir), "--set", "estimator.variant=magic"]) == 2
    assert "estimator.variant" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("estimator:\n  gps:\n    gate_chi2: 'high'\n")
    assert main(["replay", str(book_dir), "--config", str(bad)]) == 2
    assert "gate_chi2" in capsys.readouterr().err
    assert main(["replay", str(book_dir), "--sensors", "imu,sonar"]) == 1
    assert "unknown sensor" in capsys.readouterr().err


def test_a_corrupt_imu_line_is_counted_in_the_report(book_dir, tmp_path):
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(book_dir, broken)
    csv = broken / "mav0/imu0/data.csv"
    lines = csv.read_text().splitlines()
    lines[100] = lines[100].split(",")[0] + ",nan,0,0,0,0,-9.8"
    lines.insert(200, "garbage")
    csv.write_text("\n".join(lines) + "\n")
    report_path = tmp_path / "r.json"
    assert main(["-q", "replay", str(broken), "--report", str(report_path), "--no-progress"]) == 0
    assert json.loads(report_path.read_text())["skipped_lines"]["mav0/imu0/data.csv"] == 2


def test_demo_runs_both_models_side_by_side(tmp_path, capsys):
    assert main(["-q", "demo", "--duration", "30", "--out", str(tmp_path / "demo")]) == 0
    out = capsys.readouterr().out
    header = next(line for line in out.splitlines() if line.split() == ["thesis", "biases"])
    assert header
    reports = {v: json.loads((tmp_path / "demo" / f"report-{v}.json").read_text()) for v in ("thesis", "biases")}
    row = next(line for line in out.splitlines() if line.strip().startswith("position RMSE [m]"))
    assert row.split()[-2:] == [f"{reports[v]['position_rmse_m']:.4f}" for v in ("thesis", "biases")]
    for report in reports.values():  # the demo's flight is one the estimator must handle well
        assert report["position_rmse_over_gps"] < 0.8 and report["nees"]["mean_in_band"]


def test_import_euroc_from_the_command_line(euroc_mh01, tmp_path, capsys):
    out = tmp_path / "mh01"
    assert main(["-q", "import", "euroc", str(euroc_mh01), "--out", str(out), "--gps-rate", "10", "--gps-sigma", "0.02"]) == 0
    printed = capsys.readouterr().out
    assert "imu lines skipped: 7" in printed
    ds = Dataset.open(out)
    assert ds.gps() is not None and ds.truth().q is None
    assert np.median(np.diff(ds.gps().t_ns)) == pytest.approx(1e8, rel=0.05)


def test_replay_names_what_is_missing_instead_of_doing_nothing(book_dir, tmp_path, capsys):
    # --overlay with sensors that have no camera: refused, saying how to fix it
    assert main(["replay", str(book_dir), "--sensors", "imu,gps", "--overlay", str(tmp_path / "ov"), "--no-progress"]) == 1
    assert "--sensors imu,gps,camera" in capsys.readouterr().err
    # a camera asked for on a dataset without one: an error naming the file, not a warning and exit 0
    assert main(["replay", str(book_dir), "--sensors", "imu,camera,gps", "--no-progress"]) == 1
    assert "mav0/cam0/data.csv" in capsys.readouterr().err
    assert main(["replay", str(book_dir), "--overlay", str(tmp_path / "ov"), "--no-progress"]) == 1
    assert "--overlay needs the camera" in capsys.readouterr().err
    assert not (tmp_path / "ov").exists()
    # without --out or --report the replay says that nothing was written
    assert main(["-q", "replay", str(book_dir), "--no-progress"]) == 0
    assert "nothing written" in capsys.readouterr().out


def test_missing_inputs_are_named_for_what_they_are(book_dir, tmp_path, capsys):
    traj = tmp_path / "t.txt"
    assert main(["-q", "replay", str(book_dir), "--out", str(traj), "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["eval", str(traj), "--truth", str(tmp_path / "nope")]) == 1
    assert "nope: truth not found" in capsys.readouterr().err
    assert main(["eval", str(tmp_path / "none.txt"), "--truth", str(book_dir)]) == 1
    assert "none.txt: trajectory file not found" in capsys.readouterr().err
    assert main(["import", "euroc", str(tmp_path / "absent"), "--out", str(tmp_path / "x")]) == 1
    assert "absent: no such folder" in capsys.readouterr().err


def test_simulate_refuses_an_existing_dataset_before_any_work(book_dir, capsys, monkeypatch):
    import vtolpose.drivers.simulator as simulator

    def never(*args, **kwargs):
        raise AssertionError("simulated although the folder holds a dataset")

    monkeypatch.setattr(simulator, "simulate_flight", never)
    assert main(["simulate", "--duration", "5", "--out", str(book_dir)]) == 1
    assert "already holds a dataset" in capsys.readouterr().err


def test_verbosity_flags_work_after_the_subcommand(book_dir, capsys):
    assert main(["replay", str(book_dir), "-q", "--no-progress"]) == 0
    assert "INFO" not in capsys.readouterr().err
    args = build_parser().parse_args(["calibrate", "imu", "d", "-v"])
    assert args.verbose is True and args.quiet is False


def test_calibrate_imu_works_on_a_simulated_rest_with_the_defaults(tmp_path, capsys):
    out = tmp_path / "rest"
    assert main(["-q", "simulate", "--rest", "40", "--duration", "45", "--out", str(out), "--no-camera"]) == 0
    assert main(["calibrate", "imu", str(out), "--no-plot", "--out", str(tmp_path / "imu.yaml")]) == 0
    assert "gyro bias" in capsys.readouterr().out
    short = tmp_path / "short"
    assert main(["-q", "simulate", "--rest", "4", "--duration", "20", "--out", str(short), "--no-camera"]) == 0
    assert main(["calibrate", "imu", str(short), "--no-plot"]) == 1
    err = capsys.readouterr().err
    assert "at least 10 s (the shortest stretch asked for)" in err and "30 s or more" in err


def test_sub_helps_have_examples(capsys):
    for job in ("imu", "camera", "timesync", "gps-latency", "lever-arm"):
        with pytest.raises(SystemExit):
            build_parser().parse_args(["calibrate", job, "--help"])
        assert f"vtolpose calibrate {job} " in capsys.readouterr().out, job


def test_option_help_never_breaks_inside_a_token(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["replay", "--help"])
    out = capsys.readouterr().out
    for token in ("imu-gap:START:DURATION", "gps-multipath:START:DURATION:SIGMA:RATE", "clock-step:T:STEP"):
        assert token in out, token
