"""The camera's mounting (R_BC, t_BC) as filter states: its Jacobians, its place in the state, its recovery."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import central_difference
from test_landmarks import CAMERA, R_BC, T_BC, make_state
from vtolpose.estimator.core.rotation import quat_exp, quat_mul, so3_exp, so3_log
from vtolpose.estimator.core.state import CalibrationLayout
from vtolpose.estimator.vision.camera_pipeline import CameraPipeline
from vtolpose.estimator.vision.camera_update import heading_gauge, predict, stacked_update, unobservable_directions
from vtolpose.estimator.vision.landmarks import initial_landmarks, landmark_points
from vtolpose.estimator.vision.mounting import (
    MountingEstimate,
    MountingOptions,
    mounted,
    mounting_cols,
    new_landmark_columns,
)
from vtolpose.estimator.vision.time_offset import TimeOffsetEstimate, TimeOffsetOptions

RATE_B = np.array([0.4, -0.7, 1.1])
CORRECTION = np.array([0.01, -0.02, 0.015, 0.004, -0.006, 0.003])  # a mounting estimate away from the configured one


def with_mounting(time_offset: bool = False, n_landmarks: int = 4, correction: np.ndarray = CORRECTION) -> tuple:
    state = make_state(n_landmarks=n_landmarks)
    if time_offset:
        clock = TimeOffsetEstimate(TimeOffsetOptions(estimate=True, sigma_s=0.01))
        clock.value_s = 0.012
        clock.attach(state)
    mount = MountingEstimate(MountingOptions(estimate=True, rotation_sigma_deg=2.0, translation_sigma_m=0.02))
    mount.value = correction.copy()
    mount.attach(state)
    state.v = np.array([0.8, -0.5, 0.3])
    return state, mount


def test_the_layout_places_offset_rotation_and_translation_in_that_order():
    state, _ = with_mounting(time_offset=True)
    n = state.robot_dim
    assert state.calib_layout == CalibrationLayout(time_offset=True, mounting=True) and state.calib_layout.size == 7
    assert state.map_start == n + 7 and state.landmark_slice(0) == slice(n + 7, n + 13)
    np.testing.assert_array_equal(state.calib, np.r_[0.012, CORRECTION])
    np.testing.assert_array_equal(mounting_cols(state), np.arange(n + 1, n + 7))
    np.testing.assert_allclose(np.diag(state.cov)[n + 1 : n + 7], np.r_[np.full(3, math.radians(2.0) ** 2), np.full(3, 4e-4)])
    alone, _ = with_mounting()
    np.testing.assert_array_equal(mounting_cols(alone), np.arange(n, n + 6))


def test_the_filter_uses_the_estimated_mounting_and_the_injection_composes_the_rotation():
    state, _ = with_mounting()
    R_est, t_est = mounted(state, R_BC, T_BC)
    np.testing.assert_allclose(R_est, so3_exp(CORRECTION[0:3]) @ R_BC)
    np.testing.assert_allclose(t_est, T_BC + CORRECTION[3:6])
    dx = np.zeros(state.dim)
    dphi = np.array([0.3, -0.1, 0.2])  # large, so that adding rotation vectors would be visibly wrong
    dx[mounting_cols(state)] = np.r_[dphi, 0.01, 0.02, -0.03]
    state.inject(dx)
    R_new, t_new = mounted(state, R_BC, T_BC)
    np.testing.assert_allclose(R_new, so3_exp(dphi) @ R_est, atol=1e-12)  # R_BC_true = Exp(δφ) R_BC
    np.testing.assert_allclose(t_new, t_est + [0.01, 0.02, -0.03], atol=1e-15)
    np.testing.assert_allclose(state.calib_layout.minus(state.calib, CORRECTION)[0:3], so3_log(R_new @ R_est.T), atol=1e-12)


def _moved(state, dx: np.ndarray):
    """``state`` ⊞ ``dx`` over ``[δp, δθ, calibration]``."""
    moved = state.copy()
    moved.p = state.p + dx[0:3]
    moved.q = quat_mul(quat_exp(dx[3:6]), state.q)
    moved.calib = state.calib_layout.plus(state.calib, dx[6:])
    return moved


@pytest.mark.parametrize("time_offset", [False, True])
def test_measurement_jacobian_of_the_mounting_matches_central_differences(time_offset):
    state, _ = with_mounting(time_offset=time_offset)
    pred = predict(state, CAMERA, R_BC, T_BC, 1.0, RATE_B)
    c = state.calib_layout.size
    assert pred.H_pose.shape == (4, 2, 6 + c) and pred.in_image.all()
    numeric = central_difference(lambda dx: predict(_moved(state, dx), CAMERA, R_BC, T_BC, 1.0, RATE_B).uv,
                                 np.zeros(6 + c), 1e-7)
    np.testing.assert_allclose(pred.H_pose, numeric, rtol=1e-5, atol=1e-3)
    rotation = pred.H_pose[:, :, 6 + c - 6 : 6 + c - 3]
    assert np.abs(rotation).max() > 300.0  # px per radian: about the focal length, the columns are not vacuous


def test_new_landmark_jacobian_of_the_mounting_matches_central_differences():
    state, _ = with_mounting()
    R_est, t_est = mounted(state, R_BC, T_BC)
    uv = np.array([[100.0, 80.0], [400.0, 300.0], [600.0, 420.0]])
    rho0 = np.array([0.7, 1.2, 2.0])
    xn = CAMERA.undistort(uv)
    rays_c = np.column_stack([xn, np.ones(3)])
    J = new_landmark_columns(state.R, R_est, rays_c)

    def landmarks(d: np.ndarray) -> np.ndarray:
        return initial_landmarks(state.p, state.R, CAMERA, so3_exp(d[0:3]) @ R_est, t_est + d[3:6], uv, rho0)[0]

    np.testing.assert_allclose(J, central_difference(landmarks, np.zeros(6), 1e-7), atol=1e-7)
    assert np.abs(J[:, 3:5, 0:3]).max() > 0.5 and np.all(J[:, 5, :] == 0.0)  # a height or Civera prior: ρ is its own


def test_a_depth_read_off_a_map_landmark_moves_with_the_mounting():
    state, _ = with_mounting()
    R_est, t_est = mounted(state, R_BC, T_BC)
    point = landmark_points(state.landmarks[1][None, :])[0]
    xn = CAMERA.undistort(np.array([[150.0, 200.0], [500.0, 90.0]]))
    rays_c = np.column_stack([xn, np.ones(2)])

    def inverse_depths(d: np.ndarray) -> np.ndarray:  # 1/ρ = d |x|, d the reference's depth along the optical axis
        R_WC = state.R @ so3_exp(d[0:3]) @ R_est
        c_w = state.p + state.R @ (t_est + d[3:6])
        return 1.0 / (((point - c_w) @ R_WC[:, 2]) * np.linalg.norm(rays_c, axis=1))

    rho = inverse_depths(np.zeros(6))
    J = new_landmark_columns(state.R, R_est, rays_c, (point, state.p + state.R @ t_est, rho))
    np.testing.assert_allclose(J[:, 5, :], central_difference(inverse_depths, np.zeros(6), 1e-7), rtol=1e-6, atol=1e-9)
    assert np.abs(J[:, 5, :]).max() > 0.05


def test_the_mounting_is_no_unobservable_direction_and_has_no_part_in_the_heading_gauge():
    state, _ = with_mounting(time_offset=True)
    idx = np.arange(state.n_landmarks)
    N = unobservable_directions(state, idx)
    assert N.shape[0] == 6 + 7 + 6 * len(idx) and not np.any(N[6:13])
    gauge = heading_gauge(state)
    n = state.robot_dim
    assert not np.any(gauge[n : n + 7]) and np.any(gauge[state.map_start :])
    # Turning the vehicle and the map about down leaves every pixel where it was: the mounting, body-fixed, stays.
    pred = predict(state, CAMERA, R_BC, T_BC, 1.0, RATE_B)
    dx = np.zeros(state.dim)
    dx[mounting_cols(state)] = 1e-3
    assert np.abs(pred.H_pose[:, :, 7:13] @ dx[mounting_cols(state)]).max() > 0.1  # but the mounting is seen


def test_a_match_without_baseline_holds_the_mounting():
    state, _ = with_mounting(time_offset=True)
    hold = CameraPipeline._no_baseline_held(state, np.array([0, 2]))
    assert hold[state.robot_dim : state.map_start].all()


def test_the_estimate_outlives_a_state_rebuilt_for_the_robot():
    state, mount = with_mounting(time_offset=True)
    cols = mounting_cols(state)
    block = state.cov[np.ix_(cols, cols)].copy()
    block[0, 4] = block[4, 0] = 1e-6  # rotation and translation correlated
    state.cov[np.ix_(cols, cols)] = block
    mount.remember(state)
    state.robot_only(np.eye(state.robot_dim))
    assert state.calib_layout.size == 0 and state.dim == state.robot_dim
    value, sigma = mount.reading(state)
    np.testing.assert_array_equal(value, CORRECTION)
    np.testing.assert_allclose(sigma, np.sqrt(np.diag(block)))
    mount.attach(state)
    assert state.calib_layout == CalibrationLayout(mounting=True)
    np.testing.assert_array_equal(state.calib, CORRECTION)
    np.testing.assert_array_equal(state.cov[np.ix_(mounting_cols(state), mounting_cols(state))], block)


def test_without_the_option_nothing_is_estimated_or_reported():
    off = MountingEstimate(MountingOptions())
    plain = make_state()
    off.attach(plain)
    assert plain.calib.shape == (0,) and plain.calib_layout.size == 0 and off.reading(plain) is None
    R, t = mounted(plain, R_BC, T_BC)
    assert R is R_BC and t is T_BC


@pytest.mark.parametrize("key", ["rotation_sigma_deg", "translation_sigma_m"])
def test_the_prior_sigmas_must_be_positive(key):
    with pytest.raises(ValueError, match="positive"):
        MountingOptions(estimate=True, **{key: 0.0})


def test_the_full_state_smoother_refuses_the_mounting_states():
    from vtolpose.estimator.smoothing.full_state import FullStateRecorder

    state, _ = with_mounting()
    recorder = FullStateRecorder(lambda: np.arange(state.n_landmarks))
    with pytest.raises(ValueError, match="mounting"):
        recorder.before_propagation(state)


def test_a_wrong_mounting_is_recovered_over_a_synthetic_flight():
    """A camera mounted 1° about body x off what is configured, over 40 frames of a turning flight above 30 known
    ground points: the filter's rotation correction moves to +1° about x, its sigma shrinking; the translation,
    right, stays within its sigmas. A wrong sign in the Jacobian drives the estimate away."""
    from vtolpose.estimator.core.rotation import quat_from_euler
    from vtolpose.estimator.vision.landmarks import angles

    rng = np.random.default_rng(3)
    error = np.radians([1.0, 0.0, 0.0])
    R_BC_true = so3_exp(error) @ R_BC  # R_BC as configured is off by Exp(−error): the correction to find is +error
    ground = np.column_stack([rng.uniform(-1.2, 1.2, 30), rng.uniform(-1.2, 1.2, 30), np.zeros(30)])
    state = make_state(n_landmarks=0)
    n = state.robot_dim
    state.cov = np.eye(n) * 1e-4
    mount = MountingEstimate(MountingOptions(estimate=True, rotation_sigma_deg=2.0, translation_sigma_m=0.02))
    mount.attach(state)
    anchor = np.array([0.0, 0.0, -2.5])
    rays = ground - anchor
    theta, phi = angles(rays)
    state.landmarks = np.column_stack([np.tile(anchor, (30, 1)), theta, phi, 1.0 / np.linalg.norm(rays, axis=1)])
    state.cov = np.block([[state.cov, np.zeros((n + 6, 180))], [np.zeros((180, n + 6)), np.eye(180) * 1e-8]])  # the map known
    pose_q = np.r_[np.full(3, 1e-4), np.zeros(3), np.full(3, math.radians(0.1) ** 2)]  # what the IMU and GPS leave
    sigmas = []
    for k in range(40):
        t = 0.25 * k
        p_true = np.array([0.3 * math.sin(0.5 * t), 0.3 * math.cos(0.4 * t), -1.0])
        q_true = quat_from_euler(0.15 * math.sin(0.9 * t), 0.15 * math.cos(0.7 * t), 0.8 * t)
        state.p, state.q = p_true, q_true  # the pose from elsewhere, with its uncertainty
        state.cov[np.diag_indices(9)] += pose_q
        R_WB = state.R
        points_c = (ground - (p_true + R_WB @ T_BC)) @ (R_WB @ R_BC_true)
        uv, _ = CAMERA.project(points_c)
        pred = predict(state, CAMERA, R_BC, T_BC, 0.5)
        seen = np.flatnonzero(pred.in_image & CAMERA.in_image(uv))
        measured = uv[seen] + rng.normal(scale=0.5, size=(len(seen), 2))
        assert stacked_update(state, pred, seen, measured, 0.5).accepted
        sigmas.append(mount.reading(state)[1][0])
    value, sigma = mount.reading(state)
    value, sigma = np.array(value), np.array(sigma)
    truth = error
    assert abs(value[0] - truth[0]) < 0.25 * abs(truth[0]) and abs(value[0] - truth[0]) < 3.0 * sigma[0], (value, sigma)
    assert np.all(np.abs(value - np.r_[truth, 0.0, 0.0, 0.0]) < 3.0 * sigma), (value, sigma)
    assert sigmas[-1] < 0.25 * math.radians(2.0) and sigmas[-1] < sigmas[3]


def test_a_map_already_there_takes_the_mounting_error_it_was_placed_with():
    """A visual-inertial start's landmarks were placed with the mounting as configured: once the mounting states
    come, each landmark's error carries theirs (anchor with the translation, ray angles with the rotation)."""
    from vtolpose.estimator.vision.landmarks import angles, direction

    plain = make_state()
    state, mount = with_mounting()
    n, cols = state.robot_dim, mounting_cols(state)
    gain = state.cov[state.map_start :, cols] @ np.linalg.inv(mount.cov)  # how each landmark moves with the mounting
    for i, y in enumerate(state.landmarks):
        ray_b = state.R.T @ direction(y[3], y[4])

        def placed(d: np.ndarray) -> np.ndarray:
            ray = state.R @ so3_exp(d[0:3]) @ ray_b
            return np.r_[y[0:3] + state.R @ d[3:6], angles(ray), y[5]]

        np.testing.assert_allclose(gain[6 * i : 6 * i + 6], central_difference(placed, np.zeros(6), 1e-7), atol=1e-7)
    np.testing.assert_array_equal(state.cov[:n, :n], plain.cov[:n, :n])
    assert np.linalg.eigvalsh(state.cov).min() > 0.0
    bare = make_state(n_landmarks=0)
    mount.attach(bare)
    assert not np.any(bare.cov[:n, cols])


def test_a_wrong_mounting_is_found_on_a_rendered_flight_and_reported(rendered_book_dir, tmp_path):
    """The 24 s rendered book flight, IMU+camera+GPS, its R_BC given 1° wrong about body x: the filter's correction
    is −1° about x within its sigmas, and the report and the status document say so."""
    from vtolpose.config import load_config
    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.service.bench.camera_mounting import WRONG_MOUNTING, mounted_wrong
    from vtolpose.service.replay.report import build_report, summary_lines
    from vtolpose.service.replay.session import replay

    dataset = mounted_wrong(Dataset.open(rendered_book_dir), tmp_path / "wrong", WRONG_MOUNTING)
    cfg = load_config(None, {"estimator": {"camera": {"estimate_extrinsics": True}}})
    held = {}
    result = replay(dataset, cfg, ["imu", "camera", "gps"], prepare=lambda runtime: held.update(runtime=runtime))
    value, sigma = result.estimator.status().camera_mounting
    truth = -WRONG_MOUNTING
    assert sigma[0] < 0.5 * math.radians(2.0)  # learnt: from a 2° prior
    assert abs(value[0] - truth[0]) < 3.0 * sigma[0] and abs(value[0] - truth[0]) < 0.5 * abs(truth[0]), (value, sigma)
    report = build_report(result, dataset, cfg)
    runtime = held["runtime"]
    document = runtime.status.snapshot(runtime.est, runtime.fusion)
    assert document["camera_mounting"] == report["camera"]["extrinsics"]
    assert report["camera"]["extrinsics"]["rotation_deg"]["estimate"][0] == round(math.degrees(value[0]), 3)
    assert any("camera mounting beyond the configured one" in line for line in summary_lines(report))


def test_the_real_hand_held_recording_stays_a_walk_with_the_mounting_estimated(realsense_handheld, tmp_path):
    """The real RealSense recording (IMU + camera, no truth) with the option on, its default priors: the path stays
    a hand-held walk through a room (with a 2 cm translation prior it grew to 14 × 12 m) and the correction found is
    small (the rig is calibrated at the factory)."""
    pytest.importorskip("cv2", reason="the camera pipeline needs OpenCV")
    from vtolpose.config import load_config
    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.drivers.files.euroc_import import import_euroc
    from vtolpose.service.replay.session import replay

    import_euroc(realsense_handheld, tmp_path / "ds")
    cfg = load_config(None, {"calibration": {"camera": {"time_offset_s": -0.052}},
                             "estimator": {"camera": {"estimate_extrinsics": True}}})
    result = replay(Dataset.open(tmp_path / "ds"), cfg, ["imu", "camera"])
    assert result.estimator.reset_counter == 0
    p = result.trajectory.p[result.trajectory.valid]
    extent = p.max(axis=0) - p.min(axis=0)
    assert np.all(extent < 5.0) and extent.max() > 0.5, extent
    value, sigma = result.estimator.status().camera_mounting
    assert np.all(np.abs(value[0:3]) < math.radians(2.0)) and np.all(np.abs(value[3:6]) < 0.05), (value, sigma)
