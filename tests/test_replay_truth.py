"""A simulated landfill flight replayed through the daemon's own wiring (dataset.yaml → config →
``build_runtime`` → estimator → outputs), checked against physics and the simulator's truth rather
than against the code that produced it: the GPS lever arm as calibrated, and ODOMETRY's
body-frame velocity as a pymavlink peer on loopback receives it."""

import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.service.outputs.mavlink_output import mavutil
from vtolpose.service.runtime.replay_feed import run_replay

ANTENNA_B = np.array([0.0, 0.0, -0.3])  # the landfill helicopter's antenna: 0.3 m above the IMU (body FRD)


@pytest.fixture(scope="module")
def landfill():
    """40 s: on the pad, the climb-out along a 20° heading, then the first survey leg at 8 m/s."""
    return simulate_flight("landfill", 40.0, 7)


@pytest.fixture(scope="module")
def flight_dir(landfill, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("replay_truth") / "landfill"
    write_flight(landfill, root)
    return root


def truth_rotation(truth):
    """Body→world attitude of the truth at any time (SciPy, not the estimator's rotation code)."""
    return Slerp(truth.t_ns.astype(float), Rotation.from_quat(truth.q[:, [1, 2, 3, 0]]))


def fused_replay(flight_dir: Path, overrides: dict) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Positioned fused poses (time → p, q) of a replay of IMU and GPS with ``overrides`` on the defaults."""
    poses = []
    summary, _ = run_replay(Dataset.open(flight_dir), load_config(None, overrides), sensors=["imu", "gps"], speed=0.0,
                            handle_signals=False, on_fused=poses.append)
    assert summary.stopped_by == "end of data"
    return {p.t_ns: (p.p, p.q) for p in poses if p.position_initialized}


def lever_arm(values) -> dict:
    return {"calibration": {"gps": {"lever_arm_b": values}}}


def test_the_calibrated_antenna_lever_arm_reaches_the_gps_update(landfill, flight_dir):
    """Same data, three lever arms. Told the antenna is where the IMU is, the filter puts the IMU where
    the antenna is: 0.3 m higher (NED z 0.3 less) than when told the dataset's lever arm. Told the
    antenna is also 0.5 m forward, it puts the IMU 0.5 m back along the body's x axis (20° heading).
    A lever arm dropped, flipped or rotated the wrong way on its way from the dataset or the config
    to the GPS update moves these offsets by 0.3 m or more."""
    assert np.array_equal(landfill.calibration.gps.lever_arm_b, ANTENNA_B)
    calibrated = fused_replay(flight_dir, {})  # the lever arm comes from the dataset's dataset.yaml
    zeroed = fused_replay(flight_dir, lever_arm([0.0, 0.0, 0.0]))  # the config's calibration section overrides it
    forward = fused_replay(flight_dir, lever_arm([0.5, 0.0, -0.3]))
    common = sorted(set(calibrated) & set(zeroed) & set(forward))
    assert len(common) > 2000
    p_cal = np.array([calibrated[t][0] for t in common])
    r_est = Rotation.from_quat(np.array([calibrated[t][1] for t in common])[:, [1, 2, 3, 0]])
    shift_zeroed = np.array([zeroed[t][0] for t in common]) - p_cal
    shift_forward = np.array([forward[t][0] for t in common]) - p_cal
    # Where the filter puts the IMU is the fix minus R·lever: zeroing the lever moves it by +R·ANTENNA_B.
    assert np.abs(shift_zeroed - r_est.apply(ANTENNA_B)).max() < 0.1
    assert np.abs(shift_zeroed[:, 2].mean() + 0.3) < 0.02
    off_forward = shift_forward - r_est.apply([-0.5, 0.0, 0.0])
    assert np.abs(off_forward[:, 0:2]).max() < 0.05 and abs(off_forward[:, 2].mean()) < 0.02  # z: a 0.1 m transient


class OdometryPeer:
    """A pymavlink UDP endpoint on loopback that keeps every ODOMETRY it receives."""

    def __init__(self) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{self.port}", source_system=1, source_component=1)
        self.messages: list = []
        self._last_at = time.monotonic()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.conn.recv_match(type="ODOMETRY", blocking=True, timeout=0.1)
            if msg is not None:
                self.messages.append(msg)
                self._last_at = time.monotonic()

    def close(self) -> None:
        """Once what is still in flight has arrived (the stream quiet for 0.3 s, 3 s at most)."""
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline and time.monotonic() - self._last_at < 0.3:
            time.sleep(0.05)
        self._stop.set()
        self._thread.join(2.0)
        self.conn.close()


def test_odometry_velocity_is_the_truths_velocity_in_the_body_frame(landfill, flight_dir):
    """ODOMETRY vx, vy, vz against the truth's world velocity rotated into the truth's body frame at
    each message's time. Sent in the world frame instead, or rotated the wrong way, the error is
    metres per second (the climb-out and the leg fly along a 20° heading)."""
    peer = OdometryPeer()
    try:
        cfg = load_config(None, {"outputs": {"mavlink": {"enabled": True, "url": f"udpout:127.0.0.1:{peer.port}"}}})
        summary, _ = run_replay(Dataset.open(flight_dir), cfg, sensors=["imu", "gps"], speed=0.0, handle_signals=False)
        assert summary.stopped_by == "end of data"
    finally:
        peer.close()
    truth = landfill.truth
    usable = [m for m in peer.messages if m.quality > 0 and truth.t_ns[0] <= m.time_usec * 1000 <= truth.t_ns[-1]]
    assert len(usable) > 500  # of ~1850 (50 Hz over 37 s): UDP may drop some while the replay hogs the CPU
    t = np.array([m.time_usec * 1000 for m in usable])
    v_world = np.stack([np.interp(t, truth.t_ns, truth.v[:, k]) for k in range(3)], axis=1)
    v_body_true = truth_rotation(truth)(t.astype(float)).inv().apply(v_world)
    v_sent = np.array([[m.vx, m.vy, m.vz] for m in usable])
    moving = np.linalg.norm(v_world, axis=1) > 3.0
    assert moving.sum() > 150 and np.abs(v_body_true[moving, 1]).max() < 0.5  # flying forward: body vy ~ 0
    assert np.abs(v_sent - v_body_true).max() < 0.3
