"""The estimator's frame changes, through its public methods only: a GPS heard by a filter that has no world frame."""

from __future__ import annotations

import numpy as np
import pytest

from vtolpose.estimator.core import covariance
from vtolpose.estimator.core.calibration import Calibration, ImuCalibration, ImuNoise
from vtolpose.estimator.core.covariance import TH, YAW
from vtolpose.estimator.core.measurements import GpsFix
from vtolpose.estimator.filter import Estimator
from vtolpose.estimator.start import VELOCITY_FIT_S
from vtolpose.estimator.status import EventKind
from vtolpose.estimator.fusion import OutputPose
from vtolpose.estimator.vision.features import FeatureOptions, extract_features
from vtolpose.service.outputs.mavlink_odometry import odometry_fields

from test_camera_pipeline import CAM, EPOCH, textured

IMU_DT_NS = 8_000_000  # 125 Hz
STILL_F = np.array([0.0, 0.0, -9.80665])


def odometry_reset_counter(est: Estimator) -> int:
    """The ``reset_counter`` an ODOMETRY message made from the estimator's present pose carries."""
    state, cov9 = est.state, est.published_cov9()
    pose_cov = cov9[np.ix_(np.r_[0:3, 6:9], np.r_[0:3, 6:9])]
    out = OutputPose(state.t_ns, state.p, state.v, state.q, np.zeros(3), cov9, pose_cov, np.full(3, 1e-6),
                     est.heading_aligned, True, est.reset_counter, state.t_ns)
    return odometry_fields(out)["reset_counter"]


def test_a_gps_joining_a_camera_frame_of_its_own_resets_once_onto_the_fixes() -> None:
    """Started still without a heading and mapping with the camera in its own frame, the filter hears a GPS:
    it collects the fixes for VELOCITY_FIT_S, then takes their velocity and the last one's position, the
    frame jumps to the GPS's and the reset counter (the one ODOMETRY carries) rises by exactly one."""
    cal = Calibration(imu=ImuCalibration(125.0, ImuNoise.isotropic(3e-4, 2e-5, 2e-3, 3e-4)), camera=CAM)
    est = Estimator(cal)
    t_ns = EPOCH
    for _ in range(320):  # 2.5 s at rest: the static start, heading unknown
        est.process_imu(t_ns, np.zeros(3), STILL_F)
        t_ns += IMU_DT_NS
    for k, frame_t in enumerate((3_000_000_000, 3_133_333_333)):
        assert est.process_features(extract_features(textured(5 + k), EPOCH + frame_t, FeatureOptions())).accepted
    assert est.local_position and not est.heading_aligned
    before = est.reset_counter
    assert odometry_reset_counter(est) == before % 256

    p0, velocity = np.array([12.0, -7.0, 1.5]), np.array([0.5, -0.2, 0.1])
    first_fix_ns = EPOCH + 3_200_000_000
    fix_times = [first_fix_ns + k * 100_000_000 for k in range(16)]  # 10 Hz for 1.5 s
    joined_at, counters = None, []
    for fix_t in fix_times:
        while t_ns <= fix_t:
            est.process_imu(t_ns, np.zeros(3), STILL_F)
            t_ns += IMU_DT_NS
        fix = GpsFix(fix_t, p0 + velocity * (fix_t - first_fix_ns) * 1e-9, 0.02, 0.03)
        outcome = est.process_gps(fix)
        counters.append(est.reset_counter)
        if outcome is not None and outcome.reason == "GPS joined":
            assert joined_at is None, "joined twice"
            joined_at = fix_t
            assert est.state.p == pytest.approx(fix.p_ned, abs=1e-9)  # the last fix's position (no lever arm)
            assert est.state.v == pytest.approx(velocity, abs=1e-6)  # the fixes' velocity
            assert odometry_reset_counter(est) == (before + 1) % 256
    assert joined_at is not None and (joined_at - first_fix_ns) * 1e-9 == pytest.approx(VELOCITY_FIT_S)
    assert est.reset_counter == before + 1
    assert counters == [before if t < joined_at else before + 1 for t in fix_times]
    joined = [e.message for e in est.events if e.kind is EventKind.GPS_JOINED]
    assert len(joined) == 1 and f"reset #{before + 1}" in joined[0]
    assert not est.local_position



def _started_with_fixes_heard(p0: np.ndarray, velocity: np.ndarray) -> tuple[Estimator, int]:
    """A start with a second of fixes heard during the IMU's window, before there is a state: the fixes move
    (``velocity``), so it is a start in motion (heading given), its position left for the next fix."""
    cal = Calibration(imu=ImuCalibration(125.0, ImuNoise.isotropic(3e-4, 2e-5, 2e-3, 3e-4)), camera=CAM,
                      initial_heading_rad=0.3)
    est = Estimator(cal)
    t_ns, fixes = EPOCH, {EPOCH + k * 100_000_000: k for k in range(19)}  # 0–1.8 s, 10 Hz
    while not est.initialized:
        est.process_imu(t_ns, np.zeros(3), STILL_F)
        if t_ns in fixes:
            est.process_gps(GpsFix(t_ns, p0 + velocity * (t_ns - EPOCH) * 1e-9, 0.01, 0.015))
        t_ns += IMU_DT_NS
    assert not est.position_initialized and not est.local_position
    return est, t_ns


def _tilt_known(est: Estimator) -> None:
    """The tilt known to 0.06°, as gravity makes it within a second or two of a start in motion: the camera may map."""
    covariance.reinitialise(est.state.cov, TH, np.diag([1e-6, 1e-6, est.state.cov[YAW, YAW]]))


def _imu_until(est: Estimator, t_ns: int, until_ns: int) -> int:
    while t_ns <= until_ns:
        est.process_imu(t_ns, np.zeros(3), STILL_F)
        t_ns += IMU_DT_NS
    return t_ns


def test_with_a_gps_heard_the_camera_maps_only_once_the_first_fix_has_placed_the_vehicle() -> None:
    """Started with a GPS heard, the filter's position is the origin until its first fix, which moves the vehicle
    (here 14 m) and not the map: a frame in between would leave its landmarks behind, and the next frame read
    the jump as a baseline never flown. Such a frame waits (``position_pending``); the first after the fix maps,
    its anchors at the camera centre in the GPS's frame."""
    p0, velocity = np.array([12.0, -7.0, -1.5]), np.array([0.3, 0.0, 0.0])
    est, t_ns = _started_with_fixes_heard(p0, velocity)
    _tilt_known(est)
    report = est.process_features(extract_features(textured(5), EPOCH + 2_000_000_000, FeatureOptions()))
    assert not report.accepted and report.reason == "position_pending" and est.state.n_landmarks == 0
    fix_t = EPOCH + 2_100_000_000
    t_ns = _imu_until(est, t_ns, fix_t)
    placed_at = p0 + velocity * (fix_t - EPOCH) * 1e-9  # 14 m from the origin the filter had
    assert est.process_gps(GpsFix(fix_t, placed_at, 0.02, 0.03)).reason == "position initialised"
    _imu_until(est, t_ns, EPOCH + 2_200_000_000)
    _tilt_known(est)
    assert est.process_features(extract_features(textured(6), EPOCH + 2_200_000_000, FeatureOptions())).accepted
    state = est.state
    assert state.n_landmarks > 0
    camera_centre = state.p + state.R @ CAM.t_BC
    assert np.abs(state.p - placed_at).max() < 0.05
    assert np.abs(state.landmarks[:, 0:3] - camera_centre).max() < 0.01  # anchored where the camera is
    assert est.counts["camera"].rejected == {"position_pending": 1}


def test_a_gps_heard_and_gone_quiet_does_not_keep_the_camera_out() -> None:
    est, t_ns = _started_with_fixes_heard(np.array([12.0, -7.0, -1.5]), np.array([0.3, 0.0, 0.0]))
    frame_t = EPOCH + 2_900_000_000  # over gps_stale_s (1 s) since the last fix
    _imu_until(est, t_ns, frame_t)
    _tilt_known(est)
    assert est.process_features(extract_features(textured(5), frame_t, FeatureOptions())).accepted
    assert est.state.n_landmarks > 0
