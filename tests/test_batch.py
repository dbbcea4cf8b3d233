"""``vtolpose batch`` on a real Dask LocalCluster (worker processes on loopback): failures stay local,
a killed worker's flight runs elsewhere, results equal each flight run alone, unchanged flights are skipped."""

from __future__ import annotations

import csv
import json
import os
import signal
import threading
import time
from pathlib import Path

import pytest

from vtolpose.config import load_config
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.drivers.simulator.lidar import simulate_lidar
from vtolpose.service.batch.engine import local_cluster, run_in_loop, run_on_client
from vtolpose.service.batch.flights import find_flights, flight_kind
from vtolpose.service.batch.process import QualityTrack
from vtolpose.service.batch.settings import BatchSettings, EurocImport, flight_fingerprint
from vtolpose.service.batch.task import RUNNING_FILE, run_flight
from vtolpose.service.cli import main

distributed = pytest.importorskip("distributed")

OUTPUT_FILES = ("trajectory-smoothed.txt", "trajectory-filtered.txt", "covariance-smoothed.csv")
# Figures that depend on the run (where, how long), not on the flight.
RUN_FIGURES = ("wall_s", "host", "pid", "status")


@pytest.fixture(scope="module")
def flights(tmp_path_factory) -> Path:
    """Four short landfill flights (the second with its LIDAR; the last long enough to kill mid-flight)
    and one corrupt recording (its IMU file holds no valid line)."""
    root = tmp_path_factory.mktemp("flights")
    for name, duration, seed in (("f1", 12.0, 1), ("f2", 20.0, 2), ("f3", 12.0, 3), ("long", 40.0, 4)):
        flight = simulate_flight("landfill", duration, seed)
        write_flight(flight, root / name, lidar=simulate_lidar(flight) if name == "f2" else None)
    write_flight(simulate_flight("landfill", 12.0, 5), root / "corrupt")
    imu = root / "corrupt" / "mav0" / "imu0" / "data.csv"
    imu.write_bytes(imu.read_bytes().splitlines(keepends=True)[0] + b"\x00\xff garbage, not a sample\n" * 50)
    return root


@pytest.fixture(scope="module")
def settings() -> BatchSettings:
    return BatchSettings(load_config(None, {}), plots=False)


@pytest.fixture(scope="module")
def cluster():
    """One cluster for the module: two single-threaded worker processes, as `vtolpose batch --workers 2` makes."""
    with local_cluster(2, None) as c, distributed.Client(c) as client:
        yield c, client


def _kill_when_running(out: Path, name: str, killed: list[int], stop: threading.Event) -> None:
    """Kill (SIGKILL) the worker process that is writing ``name``'s partial folder, once."""
    while not stop.is_set():
        for marker in out.glob(f".{name}.partial-*/{RUNNING_FILE}"):
            try:
                pid = json.loads(marker.read_text())["pid"]
            except (OSError, ValueError):
                continue
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
            return
        time.sleep(0.01)


def _figures(row: dict) -> dict:
    return {k: v for k, v in row.items() if k not in RUN_FIGURES}


def test_a_batch_survives_a_corrupt_flight_and_a_killed_worker_and_matches_each_flight_alone(
        flights, settings, cluster, tmp_path):
    _, client = cluster
    batch = find_flights([str(flights / "*")])
    assert sorted(f.name for f in batch) == ["corrupt", "f1", "f2", "f3", "long"]
    out = tmp_path / "cluster"
    killed: list[int] = []
    stop = threading.Event()
    killer = threading.Thread(target=_kill_when_running, args=(out, "long", killed, stop), daemon=True)
    killer.start()
    seen: list[tuple[int, int, int]] = []
    try:
        rows = run_on_client(client, batch, settings, out, on_progress=lambda s, row: seen.append((s.done, s.failed, s.total)))
    finally:
        stop.set()
        killer.join()
    by_name = {row["flight"]: row for row in rows}
    assert [row["flight"] for row in rows] == [f.name for f in batch]  # in the order given
    # The corrupt recording is listed with what was wrong; no folder for it, complete or partial.
    assert by_name["corrupt"]["status"] == "failed"
    assert "imu0/data.csv" in by_name["corrupt"]["error"] and "no valid data lines" in by_name["corrupt"]["error"]
    assert not (out / "corrupt").exists()
    assert not list(out.glob(".*partial*")), "a partial folder was left behind"
    # The worker running the long flight was killed mid-flight; another process ran it to the end.
    assert len(killed) == 1
    assert by_name["long"]["status"] == "done" and by_name["long"]["pid"] != killed[0]
    assert all(by_name[n]["status"] == "done" for n in ("f1", "f2", "f3")), [(r["flight"], r["status"], r.get("error")) for r in rows]
    assert seen[-1] == (4, 1, 5)
    # The LIDAR flight has its map and volume; the others none.
    assert by_name["f2"]["volume_m3"] > 0 and (out / "f2" / "map.json").is_file()
    assert by_name["f1"]["volume_m3"] is None and not (out / "f1" / "map.json").exists()
    # Each flight run alone, in this process, gives the same files and the same figures.
    alone = tmp_path / "alone"
    single = {row["flight"]: row for row in run_in_loop(batch, settings, alone)}
    for name in ("f1", "f2", "f3", "long"):
        for file in OUTPUT_FILES:
            assert (out / name / file).read_bytes() == (alone / name / file).read_bytes(), (name, file)
        assert _figures(by_name[name]) == _figures(single[name]), name
        assert by_name[name]["duration_s"] > 10 and by_name[name]["distance_m"] is not None
        assert 0 < by_name[name]["quality_mean"] <= 100 and by_name[name]["quality_over_time"]
    assert single["corrupt"]["error"] == by_name["corrupt"]["error"]


def test_unchanged_flights_are_not_run_again_a_changed_one_is(flights, settings, cluster, tmp_path):
    _, client = cluster
    batch = [f for f in find_flights([str(flights / "*")]) if f.name in ("f1", "f3")]
    out = tmp_path / "out"
    first = run_on_client(client, batch, settings, out)
    assert [r["status"] for r in first] == ["done", "done"]
    stamp = (out / "f1" / "batch.json").stat().st_mtime_ns
    again = run_on_client(client, batch, settings, out)
    assert [r["status"] for r in again] == ["skipped", "skipped"]
    assert [_figures(r) for r in again] == [_figures(r) for r in first]
    assert (out / "f1" / "batch.json").stat().st_mtime_ns == stamp
    # New settings: every flight again. --force: again even if nothing changed.
    other = BatchSettings(load_config(None, {"estimator": {"variant": "thesis"}}), plots=False)
    assert [r["status"] for r in run_on_client(client, batch[:1], other, out)] == ["done"]
    assert [r["status"] for r in run_on_client(client, batch[:1], other, out, force=True)] == ["done"]
    assert (out / "f1" / "batch.json").stat().st_mtime_ns != stamp


def test_the_command_on_a_scheduler_started_in_the_test_writes_the_table_and_the_summary(flights, cluster, tmp_path,
                                                                                          capsys):
    import pyarrow.parquet as pq

    local, _ = cluster
    out = tmp_path / "results"
    code = main(["batch", str(flights / "f1"), str(flights / "f2"), str(flights / "corrupt"), "--out", str(out),
                 "--scheduler", local.scheduler_address, "--no-plots", "--no-progress"])
    assert code == 1  # one flight failed: said in the exit code, the others done
    text = capsys.readouterr().out
    assert "2 run, 0 unchanged, 1 failed" in text and f"on {local.scheduler_address}" in text
    assert "failed: corrupt" in text
    table = pq.read_table(out / "fleet.parquet").to_pylist()
    assert [r["flight"] for r in table] == ["f1", "f2", "corrupt"]
    assert [r["status"] for r in table] == ["done", "done", "failed"]
    assert table[1]["volume_m3"] > 0 and table[0]["volume_m3"] is None
    assert isinstance(table[0]["quality_over_time"], list) and table[0]["gps_received"] > 0
    with open(out / "fleet.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["flight"] for r in rows] == ["f1", "f2", "corrupt"] and rows[2]["error"].startswith("ValueError")
    assert float(rows[0]["duration_s"]) == table[0]["duration_s"]
    page = (out / "fleet.html").read_text()
    assert "3 flights" in page and "corrupt" in page and "no valid data lines" in page
    # Again: both done flights unchanged, the corrupt one tried again and still failing.
    assert main(["-q", "batch", str(flights / "f1"), str(flights / "f2"), str(flights / "corrupt"), "--out", str(out),
                 "--scheduler", local.scheduler_address, "--no-plots", "--no-progress"]) == 1
    assert "0 run, 2 unchanged, 1 failed" in capsys.readouterr().out


def test_the_command_starts_its_own_cluster_and_draws_the_summary(flights, tmp_path, capsys):
    pytest.importorskip("matplotlib")
    out = tmp_path / "results"
    assert main(["batch", str(flights / "f2"), "--out", str(out), "--workers", "1", "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "1 run, 0 unchanged, 0 failed" in text and "local cluster of 1 worker processes" in text
    assert (out / "f2" / "map-height.png").stat().st_size > 10_000
    assert (out / "fleet.html").read_text().count("<img src=\"data:image/png;base64,") == 4


def test_flights_are_recognised_by_their_layout(flights, tmp_path):
    (tmp_path / "euroc" / "mav0").mkdir(parents=True)
    (tmp_path / "bag").mkdir()
    (tmp_path / "bag" / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (tmp_path / "flight.mcap").write_bytes(b"")
    (tmp_path / "notes.txt").write_text("x")
    assert flight_kind(flights / "f1") == ("dataset", None)
    assert flight_kind(tmp_path / "euroc")[0] == "euroc"
    assert flight_kind(tmp_path / "bag")[0] == "rosbag" and flight_kind(tmp_path / "flight.mcap")[0] == "rosbag"
    kind, problem = flight_kind(tmp_path / "notes.txt")
    assert kind == "unknown" and "not a recording" in problem
    with pytest.raises(ValueError, match="matches no file"):
        find_flights([str(tmp_path / "nothing-*")])
    twice = find_flights([str(flights / "f1"), str(flights / "f1"), str(tmp_path / "euroc"), str(flights / "*1")])
    assert [f.name for f in twice] == ["f1", "euroc"]  # the same path once, whichever way it was named
    (tmp_path / "a" / "f1").mkdir(parents=True)
    assert [f.name for f in find_flights([str(flights / "f1"), str(tmp_path / "a" / "f1")])] == ["f1", "f1-2"]


def test_a_bag_without_topics_fails_with_what_to_give(tmp_path, settings):
    (tmp_path / "flight.mcap").write_bytes(b"not really")
    row = run_flight(find_flights([str(tmp_path / "flight.mcap")])[0], settings, str(tmp_path / "out"))
    assert row["status"] == "failed" and "--imu-topic" in row["error"]
    assert not any((tmp_path / "out").iterdir())


def test_the_fingerprint_follows_contents_and_settings(flights, settings, tmp_path):
    base = flight_fingerprint(flights / "f1", settings)
    assert flight_fingerprint(flights / "f1", settings) == base
    assert flight_fingerprint(flights / "f1", BatchSettings(settings.cfg, cell_m=2.0, plots=False)) != base
    assert flight_fingerprint(flights / "f1", BatchSettings(settings.cfg, euroc=EurocImport(seed=1), plots=False)) != base
    copy = tmp_path / "f1"
    import shutil

    shutil.copytree(flights / "f1", copy)
    assert flight_fingerprint(copy, settings) == base  # where it lies does not matter, what it holds does
    gps = copy / "mav0" / "gps0" / "data.csv"
    gps.write_bytes(gps.read_bytes().replace(b"1", b"2", 1))
    assert flight_fingerprint(copy, settings) != base


def test_quality_is_binned_in_whole_tens_of_seconds_at_most_sixty_bins():
    class Pose:
        def __init__(self, t_ns):
            self.t_ns = t_ns

    track = QualityTrack()
    import vtolpose.service.batch.process as process

    qualities = iter([0] * 300 + [80] * 10_500)
    original = process.pose_quality
    process.pose_quality = lambda pose: next(qualities)
    try:
        for k in range(10_800):  # three hours, one pose a second
            track.add(Pose(1_000_000_000 * k))
    finally:
        process.pose_quality = original
    summary = track.summary()
    assert summary["quality_bin_s"] == 180.0 and len(summary["quality_over_time"]) == 60
    assert summary["quality_over_time"][0] == 0.0 and summary["quality_over_time"][2] == 80.0
    assert summary["quality_over_time"][1] == pytest.approx(80 * 60 / 180, abs=0.1)
    assert summary["quality_usable_fraction"] == pytest.approx(10_500 / 10_800, abs=1e-4)


def test_a_flight_lost_with_its_workers_says_why():
    from vtolpose.service.batch.engine import ALLOWED_FAILURES, _lost_row
    from vtolpose.service.batch.flights import FlightInput

    flight = FlightInput("big", "/data/big", "dataset")
    row = _lost_row(flight, distributed.KilledWorker("vtolpose-flight-big", "tcp://127.0.0.1:1", ALLOWED_FAILURES), "2GB")
    assert row["status"] == "failed" and row["flight"] == "big"
    assert f"died {ALLOWED_FAILURES + 1} times" in row["error"] and "2GB per worker" in row["error"]


def test_a_bag_and_a_euroc_folder_are_imported_in_the_flight(flights, settings, tmp_path, euroc_mh01):
    """An MCAP bag of f1's streams gives f1's own smoothed trajectory; MH01 is imported with a GPS made from its truth."""
    from rosbags.rosbag2 import StoragePlugin
    from test_rosbag_import import write_bag

    from vtolpose.service.batch.settings import BagImport

    bag = tmp_path / "f1-bag"
    write_bag(flights / "f1", bag, StoragePlugin.MCAP, False, "geometry_msgs/msg/PoseStamped")
    mcap = next(bag.glob("*.mcap"))
    with_topics = BatchSettings(settings.cfg, plots=False, bag=BagImport(
        "/imu/data", "/fix", truth_topic="/truth", calibration=str(flights / "f1" / "dataset.yaml")),
        euroc=EurocImport(gps_rate_hz=10.0, camera=False))
    rows = run_in_loop(find_flights([str(mcap), str(flights / "f1"), str(euroc_mh01)]), with_topics, tmp_path / "out")
    assert [(r["kind"], r["status"]) for r in rows] == [("rosbag", "done"), ("dataset", "done"), ("euroc", "done")], rows
    bag_out, f1_out, mh01_out = (tmp_path / "out" / r["flight"] for r in rows)
    assert (bag_out / "trajectory-smoothed.txt").read_bytes() == (f1_out / "trajectory-smoothed.txt").read_bytes()
    assert not (bag_out / "dataset").exists() and not (mh01_out / "dataset").exists()  # imports are not kept
    assert rows[2]["gps_received"] > 1000 and rows[2]["smoothed_position_rmse_m"] < 0.1


def test_the_progress_line_counts_flights_and_estimates_from_those_run(capsys):
    import io

    from vtolpose.service.batch.engine import BatchState
    from vtolpose.service.commands.batch import BatchDisplay

    state = BatchState(10, workers=2)
    assert state.eta_s() is None and state.running == 2
    state.started -= 20.0  # 20 s in: two flights run, three unchanged (free), one failed
    state.done, state.skipped, state.failed = 2, 3, 1
    assert state.eta_s() == pytest.approx(20.0 / 3 * 4, rel=0.01)
    stream = io.StringIO()
    display = BatchDisplay(10, stream, enabled=True)
    display(state, {"flight": "f7", "status": "failed", "error": "ValueError: bad"})
    assert "[6/10] f7: FAILED: ValueError: bad" in capsys.readouterr().out
    line = stream.getvalue()
    assert "6/10 finished (2 run, 3 unchanged, 1 failed), 2 running, eta 27 s" in line
    state.done = 6
    assert state.running == 0


def test_the_command_line_loads_dask_and_arrow_only_for_a_batch():
    import subprocess
    import sys

    code = ("import sys; from vtolpose.service.cli import build_parser; build_parser(); "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'distributed', 'dask', 'pyarrow'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
