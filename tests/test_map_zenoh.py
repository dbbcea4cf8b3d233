"""The live mapper over Zenoh against the file path: a real service (``vtolpose run --replay``) on loopback,
the public client's ``trajectory()`` once per scan, the same map as from the service's trajectory file."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from vtolpose.client import PoseClient
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.drivers.simulator.lidar import simulate_lidar
from vtolpose.service.cli import main
from vtolpose.service.mapping.mapper import map_returns
from vtolpose.service.mapping.poses import ZenohPoses, file_window, window_poses

REPO_ROOT = Path(__file__).resolve().parents[1]
PREFIX = "vtolpose/mapper-test"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("zenoh-map") / "landfill"
    flight = simulate_flight("landfill", 40.0, 5)
    write_flight(flight, root, lidar=simulate_lidar(flight))
    return root


def test_live_map_over_zenoh_equals_the_map_from_the_trajectory_file(dataset, tmp_path):
    mapper_port, service_port = free_port(), free_port()
    traj = tmp_path / "traj.txt"
    returns = Dataset.open(dataset).lidar()
    client = PoseClient(PREFIX, listen=[f"tcp/127.0.0.1:{mapper_port}"], mode="peer", timeout_s=5.0)
    cmd = [
        sys.executable, "-m", "vtolpose", "run", "--replay", str(dataset), "--sensors", "imu,gps", "--speed", "4",
        "--hold", "--out", str(traj), "--zenoh",
        "--set", f"outputs.zenoh.prefix={PREFIX}",
        "--set", f"outputs.zenoh.listen=[tcp/127.0.0.1:{service_port}]",
        "--set", f"outputs.zenoh.connect=[tcp/127.0.0.1:{mapper_port}]",
        "--set", "outputs.zenoh.multicast_scouting=false",
        "--set", "outputs.zenoh.history_s=20",  # half the flight: a mapper that falls behind loses scans
        "--set", "smoothing.fixed_lag_s=0",  # the file holds filtered poses: so must the history (no smoothed ones)
    ]
    proc = subprocess.Popen(cmd, cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    finished = threading.Event()
    threading.Thread(target=lambda: ("replay finished" in proc.stdout.readline()) and finished.set(), daemon=True).start()
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
        a, b = live.grid.snapshot(), from_file.grid.snapshot()
        assert (a.i0, a.j0, a.height.shape) == (b.i0, b.j0, b.height.shape)
        assert np.array_equal(a.count, b.count)  # every return in the same cell
        covered = a.count > 0
        assert np.max(np.abs(a.height[covered] - b.height[covered])) < 1e-6  # TUM keeps 9 decimals

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
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(20.0)
        except subprocess.TimeoutExpired:
            proc.kill()
