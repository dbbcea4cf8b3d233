"""The live mapper over Zenoh against the file path: a real service (``vtolpose run --replay``) on loopback,
the public client's ``trajectory()`` once per scan, the same map as from the service's trajectory file; and,
waiting for smoothed poses, the same map as from the fixed-lag trajectory a smoothed replay computes."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from vtolpose.client import PoseClient
from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.drivers.simulator.lidar import simulate_lidar
from vtolpose.service.cli import main
from vtolpose.service.mapping.mapper import map_returns
from vtolpose.service.mapping.poses import ZenohPoses, file_window, trajectory_window, window_poses
from vtolpose.service.replay.smoothing import replay_smoothed

from conftest import free_port

REPO_ROOT = Path(__file__).resolve().parents[1]
PREFIX = "vtolpose/mapper-test"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("zenoh-map") / "landfill"
    flight = simulate_flight("landfill", 40.0, 5)
    write_flight(flight, root, lidar=simulate_lidar(flight))
    return root


def start_service(dataset: Path, mapper_port: int, service_port: int, *settings: str) -> tuple[subprocess.Popen, threading.Event]:
    """``vtolpose run --replay`` at 4x real time with Zenoh on loopback, connecting to the mapper; the event is
    set once it says the replay has finished (it then holds its history for queries)."""
    cmd = [
        sys.executable, "-m", "vtolpose", "run", "--replay", str(dataset), "--sensors", "imu,gps", "--speed", "4",
        "--hold", "--zenoh",
        "--set", f"outputs.zenoh.prefix={PREFIX}",
        "--set", f"outputs.zenoh.listen=[tcp/127.0.0.1:{service_port}]",
        "--set", f"outputs.zenoh.connect=[tcp/127.0.0.1:{mapper_port}]",
        "--set", "outputs.zenoh.multicast_scouting=false",
        *settings,
    ]
    proc = subprocess.Popen(cmd, cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    finished = threading.Event()
    threading.Thread(target=lambda: ("replay finished" in proc.stdout.readline()) and finished.set(), daemon=True).start()
    return proc, finished


def stop_service(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(20.0)
    except subprocess.TimeoutExpired:
        proc.kill()


def assert_same_map(a_run, b_run, tolerance_m: float) -> None:
    """Every return in the same cell, each cell's height within ``tolerance_m``."""
    a, b = a_run.grid.snapshot(), b_run.grid.snapshot()
    assert (a.i0, a.j0, a.height.shape) == (b.i0, b.j0, b.height.shape)
    assert np.array_equal(a.count, b.count)
    covered = a.count > 0
    assert np.max(np.abs(a.height[covered] - b.height[covered])) < tolerance_m


def largest_difference(a_run, b_run) -> float:
    """The largest height difference over the cells both maps cover."""
    a, b = a_run.grid.snapshot(), b_run.grid.snapshot()
    i0, j0 = max(a.i0, b.i0), max(a.j0, b.j0)
    i1, j1 = min(a.i0 + a.height.shape[0], b.i0 + b.height.shape[0]), min(a.j0 + a.height.shape[1], b.j0 + b.height.shape[1])
    cut_a = (slice(i0 - a.i0, i1 - a.i0), slice(j0 - a.j0, j1 - a.j0))
    cut_b = (slice(i0 - b.i0, i1 - b.i0), slice(j0 - b.j0, j1 - b.j0))
    both = (a.count[cut_a] > 0) & (b.count[cut_b] > 0)
    return float(np.max(np.abs(a.height[cut_a][both] - b.height[cut_b][both])))


def test_live_map_over_zenoh_equals_the_map_from_the_trajectory_file(dataset, tmp_path):
    mapper_port, service_port = free_port(), free_port()
    traj = tmp_path / "traj.txt"
    returns = Dataset.open(dataset).lidar()
    client = PoseClient(PREFIX, listen=[f"tcp/127.0.0.1:{mapper_port}"], mode="peer", timeout_s=5.0)
    proc, finished = start_service(
        dataset, mapper_port, service_port, "--out", str(traj),
        "--set", "outputs.zenoh.history_s=20",  # half the flight: a mapper that falls behind loses scans
        "--set", "smoothing.fixed_lag_s=0",  # the file holds filtered poses: so must the history (no smoothed ones)
    )
    try:
        # Live, while the replay runs at 4x: each scan is placed once the service holds final poses over it.
        source = ZenohPoses(client, wait_s=30.0)
        live = map_returns(returns, source, 1.0)
        source.close()
        assert finished.wait(60.0), proc.stderr.read() if proc.poll() is not None else "no 'replay finished'"
        assert live.scans_placed == live.scans and live.scans_not_reached == 0
        assert source.queries >= live.scans  # at least one trajectory query per scan

        from_file = map_returns(returns, window_poses(file_window(str(traj))), 1.0)
        assert from_file.scans_placed == from_file.scans
        assert_same_map(live, from_file, 1e-6)  # TUM keeps 9 decimals

        # After the flight, the command line over Zenoh (client mode): the history holds its last 20 s only,
        # so the older scans are skipped at once (the service's status says how far back it holds).
        report = tmp_path / "zenoh.json"
        assert main(["map", "--zenoh", "--connect", f"tcp/127.0.0.1:{service_port}", "--prefix", PREFIX,
                     "--lidar-from", str(dataset), "--wait", "5", "--report", str(report)]) == 0
        doc = json.loads(report.read_text())["map"]
        assert doc["scans_outside_poses"] > 50 and doc["scans_placed"] > 150 and doc["scans_not_reached"] == 0
        assert doc["scans_placed"] + doc["scans_outside_poses"] == live.scans
        assert doc["wall_s"] < 30.0
    finally:
        client.close()
        stop_service(proc)


def test_live_map_of_smoothed_poses_equals_the_map_from_the_fixed_lag_trajectory(dataset):
    """``kind="smoothed"`` waits for the daemon's fixed-lag history: the map is the one the replay's fixed-lag
    trajectory gives (the same smoother over the same data), not the filtered one."""
    mapper_port, service_port = free_port(), free_port()
    data = Dataset.open(dataset)
    returns = data.lidar()
    smoothed = replay_smoothed(data, load_config(), sensors=["imu", "gps"])  # smoothing.fixed_lag_s: the default 2 s
    lag, filtered = smoothed.smoothing.fixed_lag, smoothed.trajectory
    client = PoseClient(PREFIX, listen=[f"tcp/127.0.0.1:{mapper_port}"], mode="peer", timeout_s=5.0)
    proc, finished = start_service(dataset, mapper_port, service_port, "--set", "outputs.zenoh.history_s=60")
    try:
        source = ZenohPoses(client, wait_s=30.0, kind="smoothed")
        live = map_returns(returns, source, 1.0)
        source.close()
        assert finished.wait(60.0), proc.stderr.read() if proc.poll() is not None else "no 'replay finished'"
        assert live.scans_placed == live.scans and live.scans_not_reached == 0
        assert source.queries >= live.scans

        from_fixed_lag = map_returns(returns, window_poses(trajectory_window(lag.t_ns, lag.p, lag.q)), 1.0)
        assert_same_map(live, from_fixed_lag, 1e-6)
        from_filter = map_returns(returns, window_poses(trajectory_window(filtered.t_ns, filtered.p, filtered.q)), 1.0)
        assert largest_difference(live, from_filter) > 0.01  # not the filtered map
    finally:
        client.close()
        stop_service(proc)

    with pytest.raises(ValueError, match="kind"):
        ZenohPoses(client, kind="predicted")
