"""The camera's residual time offset as a filter state: its Jacobian, its place in the state, its recovery."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import central_difference
from test_landmarks import CAMERA, R_BC, T_BC, make_state
from vtolpose.estimator.core import covariance
from vtolpose.estimator.core.rotation import quat_exp, quat_mul
from vtolpose.estimator.core.state import NO_CALIBRATION
from vtolpose.estimator.vision.camera_update import _stacked_jacobian, predict, unobservable_directions
from vtolpose.estimator.vision.time_offset import TimeOffsetEstimate, TimeOffsetOptions, at_frame_time

RATE_B = np.array([0.4, -0.7, 1.1])  # rad/s: a turn fast enough for the offset to matter


def with_offset(t_d: float, n_landmarks: int = 4) -> tuple:
    state = make_state(n_landmarks=n_landmarks)
    clock = TimeOffsetEstimate(TimeOffsetOptions(estimate=True, sigma_s=0.01))
    clock.value_s = t_d
    clock.attach(state)
    return state, clock


def test_the_offset_state_sits_between_the_robot_and_the_map_uncorrelated():
    plain = make_state()
    state, _ = with_offset(0.004)
    n = state.robot_dim
    assert state.map_start == n + 1 and state.dim == plain.dim + 1
    np.testing.assert_array_equal(state.cov[n, :], np.r_[np.zeros(n), 1e-4, np.zeros(plain.dim - n)])
    keep = np.r_[0:n, n + 1 : state.dim]
    np.testing.assert_array_equal(state.cov[np.ix_(keep, keep)], plain.cov)
    np.testing.assert_array_equal(state.landmarks[1], plain.landmarks[1])
    assert state.landmark_slice(0) == slice(n + 1, n + 7)


def test_pixels_are_predicted_at_the_pose_the_frame_saw():
    state, _ = with_offset(0.02)
    shifted = state.copy()
    shifted.calib, shifted.calib_layout = shifted.calib[:0], NO_CALIBRATION
    shifted.cov = covariance.keep_states(state.cov, np.r_[0 : state.robot_dim, state.map_start : state.dim])
    shifted.p = state.p + 0.02 * state.v
    shifted.q = quat_mul(state.q, quat_exp(0.02 * RATE_B))
    np.testing.assert_allclose(predict(state, CAMERA, R_BC, T_BC, 1.0, RATE_B).uv,
                               predict(shifted, CAMERA, R_BC, T_BC, 1.0).uv, atol=1e-9)
    assert at_frame_time(shifted, RATE_B) is shifted  # no offset state: the pose as it is


def test_offset_and_pose_jacobians_match_central_differences():
    state, _ = with_offset(0.015)
    state.v = np.array([0.8, -0.5, 0.3])
    pred = predict(state, CAMERA, R_BC, T_BC, 1.0, RATE_B)
    assert pred.H_pose.shape == (4, 2, 7) and pred.in_image.all()

    def pixels(dx: np.ndarray) -> np.ndarray:
        moved = state.copy()
        moved.p = state.p + dx[0:3]
        moved.q = quat_mul(quat_exp(dx[3:6]), state.q)
        moved.calib = state.calib + dx[6:7]
        return predict(moved, CAMERA, R_BC, T_BC, 1.0, RATE_B).uv

    numeric = central_difference(pixels, np.zeros(7), 1e-7)
    np.testing.assert_allclose(pred.H_pose, numeric, rtol=1e-5, atol=1e-3)
    assert np.abs(pred.H_pose[:, :, 6]).max() > 50.0  # px per second: the column is not vacuous


def test_innovation_covariance_includes_the_offset():
    state, _ = with_offset(0.0, n_landmarks=3)
    state.cov[state.robot_dim, 0:3] = state.cov[0:3, state.robot_dim] = 1e-5  # offset correlated with position
    pred = predict(state, CAMERA, R_BC, T_BC, 0.7, RATE_B)
    for j in range(3):
        cols, H = _stacked_jacobian(state, np.array([j]), pred.H_pose[[j]], pred.H_landmark[[j]])
        full = np.zeros((2, state.dim))
        full[:, cols] = H
        np.testing.assert_allclose(pred.S[j], full @ state.cov @ full.T + 0.49 * np.eye(2), rtol=1e-10, atol=1e-12)


def test_the_offset_is_no_unobservable_direction():
    state, _ = with_offset(0.0)
    idx = np.arange(state.n_landmarks)
    N = unobservable_directions(state, idx)
    assert N.shape[0] == 7 + 6 * len(idx) and not np.any(N[6])


def test_the_estimate_outlives_a_state_rebuilt_for_the_robot():
    state, clock = with_offset(0.0)
    state.calib = np.array([-0.008])
    state.cov[state.robot_dim, state.robot_dim] = 4e-6
    clock.remember(state)
    state.robot_only(np.eye(state.robot_dim))
    assert state.n_landmarks == 0 and state.dim == state.robot_dim
    assert clock.reading(state) == pytest.approx((-0.008, 0.002))
    clock.attach(state)
    assert state.calib[0] == -0.008 and state.cov[state.robot_dim, state.robot_dim] == 4e-6


def test_a_wrong_configured_offset_is_recovered_on_a_rendered_flight(rendered_book_dir):
    """The 24 s rendered book flight, IMU+camera+GPS, its frames stamped 10 ms late: the filter finds −10 ms."""
    from vtolpose.config import load_config
    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.service.replay.session import replay

    dataset = Dataset.open(rendered_book_dir)
    cfg = load_config(None, {"calibration": {"camera": {"time_offset_s": 0.010}},
                             "estimator": {"camera": {"estimate_time_offset": True, "time_offset_sigma_s": 0.02}}})
    held = {}
    status = replay(dataset, cfg, ["imu", "camera", "gps"], prepare=lambda runtime: held.update(runtime=runtime)).estimator.status()
    estimate, sigma = status.camera_time_offset_s
    assert sigma < 0.001  # learnt: from a 20 ms prior
    assert abs(estimate + 0.010) < 3.0 * sigma, (estimate, sigma)
    runtime = held["runtime"]
    document = runtime.status.snapshot(runtime.est, runtime.fusion)  # the service's status document
    assert document["camera_time_offset_ms"] == {"estimate": round(estimate * 1e3, 3), "sigma": round(sigma * 1e3, 3)}


def test_without_the_option_nothing_is_estimated_or_reported():
    off = TimeOffsetEstimate(TimeOffsetOptions(estimate=False))
    plain = make_state()
    off.attach(plain)
    assert plain.calib.shape == (0,) and plain.dim == make_state().dim
    assert off.reading(plain) is None


def test_the_heading_gauge_turns_the_map_where_it_sits_behind_the_offset():
    """The turn about down that the camera cannot see moves the landmarks, wherever the offset state puts them,
    and not the offset itself."""
    from vtolpose.estimator.vision.camera_update import heading_gauge

    plain = make_state()
    state, _ = with_offset(0.004)
    n = state.robot_dim
    with_clock, without = heading_gauge(state), heading_gauge(plain)
    assert with_clock[n] == 0.0
    np.testing.assert_array_equal(np.r_[with_clock[:n], with_clock[n + 1 :]], without)
