"""Start-up on real motion, simulated: a pose at once, the heading placed once the motion shows it.

Three helicopter flights built here from the simulator's path segments (no scenario option):
switched on already flying a course with turns; switched on on the pad, climbing straight up
before it flies off; and one that only ever goes up and hovers, so that its heading can never
be seen. The IMU is the simulator's Crossbow-class unit with a gyro turn-on bias of 3 °/s (a
MEMS gyro's, not a calibrated one), the GPS 10 Hz with σ_xy 5 cm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from vtolpose.drivers.simulator.flight import sample_times_ns
from vtolpose.drivers.simulator.gps_model import GpsErrorModel, antenna_positions, gps_errors
from vtolpose.drivers.simulator.imu_model import ImuErrorModel, corrupt_imu
from vtolpose.drivers.simulator.trajectory import AlongTrack, Hold, Segment, SegmentPath, SmoothMove, ThrustAlignedTrajectory, Turn
from vtolpose.estimator.core.calibration import STANDARD_GRAVITY, Calibration, GpsCalibration, ImuCalibration
from vtolpose.estimator.core.measurements import GpsFix
from vtolpose.estimator.core.covariance import YAW
from vtolpose.estimator.core.rotation import rotation_angle, yaw_of
from vtolpose.estimator.filter import Estimator, FilterOptions
from vtolpose.estimator.inertial.heading_bank import UNKNOWN_HEADING_VAR
from vtolpose.estimator.inertial.initializer import InitOptions

EPOCH = 1_000_000_000
IMU = ImuErrorModel(rate_hz=200.0, gyro_turn_on_bias_std=float(np.deg2rad(3.0)))
GPS = GpsErrorModel(sigma_h=0.05, rate_hz=10.0)
FILTER = FilterOptions(init=InitOptions(estimate_gravity=False))  # as the service sets the biases model up


@dataclass
class Run:
    """What the estimator published at each IMU sample once it had started."""

    t_s: np.ndarray
    aligned: np.ndarray
    positioned: np.ndarray
    p: np.ndarray
    q: np.ndarray
    heading_var: np.ndarray
    est: Estimator
    truth_p: np.ndarray
    truth_q: np.ndarray

    def first(self, mask: np.ndarray) -> float:
        return float(self.t_s[np.argmax(mask)]) if np.any(mask) else np.inf


def fly(segments: list[Segment], seed: int) -> Run:
    """Simulate the path (IMU, GPS, truth) and feed it to an estimator that knows no heading."""
    path = SegmentPath(tuple(segments))
    trajectory = ThrustAlignedTrajectory(path, STANDARD_GRAVITY)
    t_imu = sample_times_ns(IMU.rate_hz, path.duration_s, EPOCH)
    at_imu = trajectory.kinematics((t_imu - EPOCH) * 1e-9)
    rng = np.random.default_rng(seed)
    imu = corrupt_imu(at_imu.omega_b(), at_imu.specific_force_b(STANDARD_GRAVITY), IMU, rng)
    t_gps = sample_times_ns(GPS.rate_hz, path.duration_s, EPOCH)
    at_gps = trajectory.kinematics((t_gps - EPOCH) * 1e-9)
    fixes = antenna_positions(at_gps.p, at_gps.rotation(), GPS) + gps_errors((t_gps - EPOCH) * 1e-9, GPS, rng)
    calibration = Calibration(ImuCalibration(IMU.rate_hz, IMU.noise()), GpsCalibration())
    est = Estimator(calibration, FILTER)
    rows, j = [], 0
    for k, t in enumerate(t_imu):
        while j < len(t_gps) and t_gps[j] <= t:
            est.process_gps(GpsFix(int(t_gps[j]), fixes[j], GPS.sigma_h, GPS.sigma_v))
            j += 1
        est.process_imu(int(t), imu.gyro[k], imu.accel[k])
        state = est.state
        if state is not None:  # the pose as published: the heading's variance that of an unknown one until placed
            rows.append((k, est.heading_aligned, est.position_initialized, state.p.copy(), state.q.copy(),
                         est.published_cov9()[YAW, YAW]))
    k, aligned, positioned, p, q, var = (np.array(x) for x in zip(*rows))
    return Run((t_imu[k] - EPOCH) * 1e-9, aligned, positioned, p, q, var, est, at_imu.p[k], at_imu.q()[k])


def course(start: np.ndarray, heading: float, duration_s: float, speed: float = 4.0) -> list[Segment]:
    """Legs that speed up and slow down (2 <-> 5 m/s) joined by 90° turns to either side, for ``duration_s``:
    a survey flown by hand, with accelerations along and across the track."""
    segments: list[Segment] = [AlongTrack("leg", 5.0, start, heading, speed, 5.0)]
    k = 0
    while sum(s.duration_s for s in segments) < duration_s:
        p, h = segments[-1].end()
        v = 5.0 if k % 2 == 0 else 2.0
        segments.append(Turn("turn", 5.0, p, h, v, (np.pi / 2) * (1 if k % 4 < 2 else -1)))
        p, h = segments[-1].end()
        segments.append(AlongTrack("leg", 5.0, p, h, v, 2.0 if v == 5.0 else 5.0))
        k += 1
    return segments


def heading_error(run: Run) -> np.ndarray:
    return np.abs(np.angle(np.exp(1j * (yaw_of(run.q) - yaw_of(run.truth_q)))))


@pytest.fixture(scope="module")
def moving() -> Run:
    """Switched on in forward flight at 4 m/s, turning every few seconds."""
    return fly(course(np.array([0.0, 0.0, -30.0]), 0.7, 60.0), seed=11)


@pytest.fixture(scope="module")
def vertical_first() -> Run:
    """On the pad for 5 s, 20 s straight up by 30 m, then off along a course."""
    pad = np.array([0.0, 0.0, -0.8])
    climb = [Hold("pad", 5.0, pad, 2.0), SmoothMove("climb", 20.0, pad, 2.0, np.array([0.0, 0.0, -30.0]))]
    top, heading = climb[-1].end()
    accelerate = AlongTrack("accelerate", 6.0, top, heading, 0.0, 4.0)
    return fly(climb + [accelerate] + course(accelerate.end()[0], heading, 30.0), seed=12)


@pytest.fixture(scope="module")
def never_horizontal() -> Run:
    """On the pad, straight up by 20 m, then a minute of hover: no horizontal acceleration, ever."""
    pad = np.array([0.0, 0.0, -0.8])
    climb = SmoothMove("climb", 15.0, pad, -1.0, np.array([0.0, 0.0, -20.0]))
    return fly([Hold("pad", 5.0, pad, -1.0), climb, Hold("hover", 60.0, climb.end()[0], -1.0)], seed=13)


def test_a_flight_that_starts_moving_gets_a_pose_at_once_and_its_heading_within_seconds(moving):
    started = moving.first(moving.positioned)
    assert started < 3.5  # max_wait_s of IMU, then the next fix
    assert not moving.aligned[moving.positioned][0]  # first a pose without a heading ...
    assert moving.heading_var[moving.positioned][0] == pytest.approx(UNKNOWN_HEADING_VAR)  # ... and said so
    placed = moving.first(moving.aligned)
    assert placed - started < 20.0 and moving.est.reset_counter == 0
    # A moving start (tilt from the mean specific force, gyro bias unknown) leaves the filter somewhat
    # optimistic about its heading for a while after the placement (README, known limits).
    after = moving.aligned
    assert np.mean(heading_error(moving)[after] < 3.0 * np.sqrt(moving.heading_var[after])) > 0.85
    late = moving.t_s > placed + 20.0
    assert np.degrees(np.sqrt(np.mean(rotation_angle(moving.q[late], moving.truth_q[late]) ** 2))) < 1.0
    assert np.sqrt(np.mean(np.sum((moving.p[late] - moving.truth_p[late]) ** 2, axis=1))) < 0.05


def test_vertical_motion_alone_leaves_the_heading_unknown_until_the_vehicle_flies_off(vertical_first):
    run = vertical_first
    assert run.first(run.positioned) < 3.0  # still on the pad: it starts from the still window
    climbing = run.t_s < 25.0
    assert not np.any(run.aligned[climbing])  # a climb shows no heading, and none is guessed
    assert np.allclose(run.heading_var[climbing & run.positioned], UNKNOWN_HEADING_VAR)
    placed = run.first(run.aligned)
    assert placed - 25.0 < 20.0 and run.est.reset_counter == 0
    after = run.aligned
    assert np.mean(heading_error(run)[after] < 3.0 * np.sqrt(run.heading_var[after])) > 0.95
    # Position all along, heading or not.
    on = run.positioned
    assert np.sqrt(np.mean(np.sum((run.p[on] - run.truth_p[on]) ** 2, axis=1))) < 0.06


def test_a_flight_that_never_accelerates_horizontally_never_claims_a_heading(never_horizontal):
    run = never_horizontal
    assert run.first(run.positioned) < 3.0
    assert not np.any(run.aligned) and run.est.heading_placement is None and run.est.reset_counter == 0
    assert np.allclose(run.heading_var[run.positioned], UNKNOWN_HEADING_VAR)
    on = run.positioned
    assert np.sqrt(np.mean(np.sum((run.p[on] - run.truth_p[on]) ** 2, axis=1))) < 0.06
    # Roll and pitch are known without the heading: levelled by gravity and the still pad.
    tilt = np.degrees(rotation_angle(run.q[on], run.truth_q[on]))  # includes the arbitrary heading ...
    heading = np.degrees(heading_error(run)[on])
    assert np.all(np.abs(tilt - heading) < 2.0)  # ... which is all of the difference


def test_the_replay_report_scores_attitude_once_the_heading_is_placed(tmp_path) -> None:
    from vtolpose.config import load_config
    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.drivers.simulator import simulate_flight
    from vtolpose.drivers.simulator.export import write_flight
    from vtolpose.service.replay.report import build_report, summary_lines
    from vtolpose.service.replay.session import replay

    write_flight(simulate_flight("book", 30.0, 2), tmp_path / "book")
    dataset = Dataset.open(tmp_path / "book")
    cfg = load_config(None, {"estimator": {"heading": {"source": "gps"}}})  # the dataset's heading unused
    report = build_report(replay(dataset, cfg, ["imu", "gps"]), dataset, cfg)
    assert report["heading_source"] == "heading bank" and report["heading_placement"]["sigma_deg"] < 10.0
    assert report["attitude_rmse_with_heading_deg"] < 2.0 < report["attitude_rmse_deg"]  # before: any heading
    assert "once the heading is placed" in summary_lines(report)[2]
