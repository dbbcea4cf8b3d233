"""``vtolpose run``: a replay through the daemon with real peers on loopback (a Zenoh client in this
process, a pymavlink endpoint), SIGTERM, the same trajectory as the offline replay, config errors."""

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.drivers.files.tum import read_tum, write_tum
from vtolpose.estimator.pose_history import interpolate_rows
from vtolpose.estimator.core.rotation import rotation_angle
from vtolpose.service.cli import main
from vtolpose.service.outputs.mavlink_output import mavutil
from vtolpose.service.outputs.pose_client import PoseClient, PoseUnavailable
from vtolpose.service.replay.session import replay
from vtolpose.service.runtime.replay_feed import run_replay

from conftest import free_port

REPO_ROOT = Path(__file__).resolve().parents[1]
mav = mavutil.mavlink


def can_bind(port: int, kind: int = socket.SOCK_STREAM) -> bool:
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


@pytest.fixture(scope="module")
def flight_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("run") / "landfill"
    write_flight(simulate_flight("landfill", 30.0, 7), root)
    return root


def test_replay_through_the_runtime_equals_the_offline_replay(flight_dir, tmp_path):
    dataset = Dataset.open(flight_dir)
    cfg = load_config()
    summary, runtime = run_replay(dataset, cfg, sensors=["imu", "gps"], speed=0.0,
                                  trajectory_path=tmp_path / "runtime.txt", handle_signals=False)
    offline = replay(Dataset.open(flight_dir), cfg, ["imu", "gps"])
    write_tum(tmp_path / "offline.txt", offline.trajectory.t_ns, offline.trajectory.p, offline.trajectory.q)
    assert (tmp_path / "runtime.txt").read_bytes() == (tmp_path / "offline.txt").read_bytes()
    assert summary.stopped_by == "end of data" and summary.trajectory_lines == len(offline.trajectory.t_ns)
    assert runtime.est.counts_report() == offline.estimator.counts_report()


class MavlinkListener:
    """A pymavlink UDP endpoint collecting messages on a thread."""

    def __init__(self, port: int) -> None:
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=1)
        self.messages: list = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.1)
            if msg is not None:
                self.messages.append(msg)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.conn.close()


def test_daemon_replay_with_real_peers_then_sigterm(flight_dir, tmp_path):
    zenoh_client_port, zenoh_listen_port, mav_port = free_port(), free_port(), free_port(socket.SOCK_DGRAM)
    traj = tmp_path / "traj.txt"
    listener = MavlinkListener(mav_port)
    client = PoseClient("vtolpose/vtol1", listen=[f"tcp/127.0.0.1:{zenoh_client_port}"], mode="peer", timeout_s=10.0)
    poses, status = [], []
    client.subscribe(poses.append)
    client.session.declare_subscriber("vtolpose/vtol1/status", lambda s: status.append(json.loads(s.payload.to_string())))
    cmd = [
        sys.executable, "-m", "vtolpose", "run", "--replay", str(flight_dir), "--speed", "15", "--hold",
        "--out", str(traj), "--mavlink", f"udpout:127.0.0.1:{mav_port}", "--zenoh",
        "--set", f"outputs.zenoh.listen=[tcp/127.0.0.1:{zenoh_listen_port}]",
        "--set", f"outputs.zenoh.connect=[tcp/127.0.0.1:{zenoh_client_port}]",
        "--set", "outputs.zenoh.multicast_scouting=false",
        "--set", "fusion.delay_s=0.0",  # ODOMETRY at a filter step is then the fused pose in the file
        "--set", "smoothing.fixed_lag_s=0",  # pose/at answers the filtered poses of the file (smoothing: test_smoothing_zenoh)
    ]
    proc = subprocess.Popen(cmd, cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        ready = proc.stdout.readline()  # printed once the replay is done and the estimate is final
        assert "replay finished" in ready, ready + proc.stderr.read() if proc.poll() is not None else ready
        t_file, p_file, q_file = read_tum(traj)
        assert len(t_file) > 1000

        # Zenoh: poses arrived in this (separate) process, in order.
        assert len(poses) > 500
        assert all(b.seq > a.seq and b.t_ns > a.t_ns for a, b in zip(poses, poses[1:]))
        assert poses[-1].status == "ok" and poses[-1].origin is not None
        assert status and status[-1]["outputs"]["mavlink"]["odometry_sent"] > 100
        assert status[-1]["outputs"]["zenoh"]["poses_published"] > 500 and status[-1]["sensors"]["gps"]["total"] > 0

        # pose/at between two estimates: the interpolation of the file's neighbours.
        k = len(t_file) // 2
        t_mid = int(t_file[k] + (t_file[k + 1] - t_file[k]) * 0.3)
        pose = client.pose_at(t_mid)
        rows = np.hstack([p_file, q_file])
        expected = interpolate_rows(t_file, np.pad(rows, ((0, 0), (0, 42))), np.array([t_mid]))[0]
        assert np.linalg.norm(pose.p - expected[0:3]) < 1e-3
        assert np.degrees(rotation_angle(pose.q, expected[3:7])) < 0.01
        started = time.monotonic()
        with pytest.raises(PoseUnavailable, match="outside the history"):
            client.pose_at(int(t_file[0]) - 1_000_000_000)
        assert time.monotonic() - started < 5.0
        window = client.trajectory(int(t_file[k]), int(t_file[k + 50]))
        assert np.array_equal(window.t_ns, t_file[k:k + 51])

        # MAVLink: HEARTBEAT and ODOMETRY; ODOMETRY at a filter step equals the file's pose there.
        beats = [m for m in listener.messages if m.get_type() == "HEARTBEAT"]
        odometry = [m for m in listener.messages if m.get_type() == "ODOMETRY"]
        assert beats and beats[-1].type == mav.MAV_TYPE_ONBOARD_CONTROLLER and beats[-1].get_srcComponent() == 197
        assert len(odometry) > 100
        # An update reaches the published pose one sample after its time (the pose leaves before the
        # filter's work): skip the IMU sample at or just after each fix, where the file already has it.
        # Updates the filter makes by itself (at rest: zero velocity) are rare; allow a few of those.
        data = Dataset.open(flight_dir)
        imu_t = data.imu().t_ns
        after_fix = set(imu_t[np.searchsorted(imu_t, data.gps().t_ns)[:-1]].tolist())
        index = {int(t): i for i, t in enumerate(t_file) if int(t) not in after_fix}
        matched = off = 0
        for m in odometry:
            i = index.get(m.time_usec * 1000)
            if i is None or m.quality == 0:
                continue
            matched += 1
            err_m = np.linalg.norm(np.array([m.x, m.y, m.z]) - p_file[i])
            err_deg = np.degrees(rotation_angle(np.array(m.q, dtype=float), q_file[i]))
            assert err_m < 0.05 and err_deg < 0.1  # at most one filter update apart
            off += err_m > 1e-4 or err_deg > 1e-3
            assert (m.frame_id, m.child_frame_id, m.estimator_type) == (
                mav.MAV_FRAME_LOCAL_NED, mav.MAV_FRAME_BODY_FRD, mav.MAV_ESTIMATOR_TYPE_VIO)
            assert np.all(np.isfinite(m.pose_covariance)) and m.pose_covariance[0] > 0
        assert matched > 50 and off <= 0.02 * matched

        # SIGTERM: clean exit, trajectory complete, ports released.
        lines_before = traj.read_text().count("\n")
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err
        assert "stopped by signal" in out
        text = traj.read_text()
        assert text.endswith("\n") and text.count("\n") == lines_before == len(t_file) + 1
        assert f"{len(t_file)} trajectory lines" in out
        assert can_bind(zenoh_listen_port)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        client.close()
        listener.close()


@pytest.mark.parametrize(
    "args, message",
    [
        (["--set", "outputs.zenoh.lisen=[]"], "unknown key 'outputs.zenoh.lisen'"),
        (["--set", "outputs.mavlink.rate_hz=fast"], "key 'outputs.mavlink.rate_hz': expected a finite number"),
        (["--mavlink", "udpout:127.0.0.1:70000"], "key 'outputs.mavlink.url': port '70000'"),
        (["--mavlink", "ttyUSB0"], "key 'outputs.mavlink.url'"),
        (["--set", "outputs.zenoh.connect=[tcp/127.0.0.1]"], "key 'outputs.zenoh.connect': endpoint 'tcp/127.0.0.1'"),
        (["--set", "outputs.zenoh.listen=[carrier-pigeon/x:1]"], "key 'outputs.zenoh.listen'.*unknown protocol"),
        (["--set", "outputs.zenoh.prefix=vtolpose/*"], "key 'outputs.zenoh.prefix'"),
        (["--set", "outputs.mavlink.require_signing=true"], "key 'outputs.mavlink.require_signing'"),
        (["--speed", "-1"], "key 'replay.speed': must be at least 0"),
    ],
)
def test_bad_configuration_is_refused_naming_the_key(flight_dir, tmp_path, capsys, args, message):
    out = tmp_path / "traj.txt"
    assert main(["run", "--replay", str(flight_dir), "--out", str(out), *args]) == 2
    assert __import__("re").search(message, capsys.readouterr().err)
    assert not out.exists()  # refused before anything was opened


def test_an_output_that_cannot_open_is_named(flight_dir, tmp_path, capsys):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        code = main(["run", "--replay", str(flight_dir), "--zenoh", "--set", f"outputs.zenoh.listen=[tcp/127.0.0.1:{port}]",
                     "--set", "outputs.zenoh.multicast_scouting=false"])
    assert code == 1 and "the zenoh output could not open" in capsys.readouterr().err


def test_bad_configuration_file_and_missing_calibration(tmp_path, capsys):
    cfg = tmp_path / "vehicle.yaml"
    cfg.write_text("outputs:\n  zenoh:\n    enabled: true\n    listen: [tcp/0.0.0.0:99999]\n")
    assert main(["run", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert f"config file {cfg}" in err and "outputs.zenoh.listen" in err and "99999" in err
    assert main(["run"]) == 2
    assert "key 'run.calibration_file'" in capsys.readouterr().err


def test_sigint_mid_replay_flushes_and_releases_ports(flight_dir, tmp_path):
    traj, udp_port, tcp_port = tmp_path / "traj.txt", free_port(socket.SOCK_DGRAM), free_port()
    cmd = [sys.executable, "-m", "vtolpose", "run", "--replay", str(flight_dir), "--speed", "3", "--out", str(traj),
           "--mavlink", f"udpin:127.0.0.1:{udp_port}", "--zenoh", "--set", f"outputs.zenoh.listen=[tcp/127.0.0.1:{tcp_port}]",
           "--set", "outputs.zenoh.multicast_scouting=false"]
    proc = subprocess.Popen(cmd, cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and proc.poll() is None:  # until the filter is writing poses
            if traj.exists() and traj.stat().st_size > 2000:
                break
            time.sleep(0.05)
        assert not can_bind(udp_port, socket.SOCK_DGRAM) and not can_bind(tcp_port)  # in use while running
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "stopped by signal" in out
    lines = int(out.split(" trajectory lines")[0].rsplit(" ", 1)[1])
    text = traj.read_text()
    assert text.endswith("\n") and text.count("\n") == lines + 1 and lines > 0
    assert can_bind(udp_port, socket.SOCK_DGRAM) and can_bind(tcp_port)
