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
    assert main(["eval", str(traj), "--truth", str(book_dir)]) == 0
    scores = json.loads(capsys.readouterr().out)
    assert scores["position_rmse_m"] == pytest.approx(report["position_rmse_m"], rel=1e-6)


def test_replay_variant_and_set_override(book_dir, tmp_path):
    report_path = tmp_path / "r.json"
    main(["-q", "replay", str(book_dir), "--variant", "thesis", "--set", "estimator.gps.gate_chi2=11.34", "--report", str(report_path), "--no-progress"])
    report = json.loads(report_path.read_text())
    assert report["variant"] == "thesis"


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


def test_demo_runs_both_models(tmp_path, capsys):
    assert main(["-q", "demo", "--duration", "30", "--out", str(tmp_path / "demo")]) == 0
    out = capsys.readouterr().out
    assert "variant thesis" in out and "variant biases" in out
    assert (tmp_path / "demo" / "report-biases.json").is_file()


def test_import_euroc_from_the_command_line(euroc_mh01, tmp_path, capsys):
    out = tmp_path / "mh01"
    assert main(["-q", "import", "euroc", str(euroc_mh01), "--out", str(out), "--gps-rate", "10", "--gps-sigma", "0.02"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["imu_lines_skipped"] == 7
    ds = Dataset.open(out)
    assert ds.gps() is not None and ds.truth().q is None
    assert np.median(np.diff(ds.gps().t_ns)) == pytest.approx(1e8, rel=0.05)
