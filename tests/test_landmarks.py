"""Inverse-depth landmarks: direction convention, measurement and initialisation Jacobians, covariance."""

from __future__ import annotations

import numpy as np
import pytest

from vtolpose.estimator.core.calibration import CameraCalibration
from vtolpose.estimator.vision.camera_model import CameraModel
from vtolpose.estimator.vision.camera_update import (
    _stacked_jacobian, carry_gauge, heading_gauge, iterated_update, observability_constrained, predict, predict_h, stacked_update,
    unobservable_directions,
)
from vtolpose.estimator.vision.landmarks import (
    ROBOT_POSE_COLS,
    add_landmarks,
    angles,
    angles_jacobian,
    direction,
    initial_landmarks,
    landmark_points,
    point_jacobian,
    remove_landmarks,
    world_rays,
)
from vtolpose.estimator.core.measurements import GpsFix
from vtolpose.estimator.gnss.gps_update import GpsUpdater
from vtolpose.estimator.core.rotation import quat_conj, quat_exp, quat_from_euler, quat_log, quat_mul
from vtolpose.estimator.vision.camera_pipeline import CameraPipeline
from vtolpose.estimator.core.state import FilterState, StateLayout

R_BC = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
T_BC = np.array([0.05, 0.01, 0.05])
CAMERA = CameraModel(CameraCalibration(656, 494, 570.0, 570.0, 327.5, 246.5, np.array([-0.12, 0.05, 5e-4, -3e-4, 0.0])))


def make_state(variant: str = "biases", n_landmarks: int = 4, seed: int = 0) -> FilterState:
    rng = np.random.default_rng(seed)
    s = FilterState(StateLayout(variant))
    s.p = np.array([0.1, -0.2, -0.8])
    s.v = rng.normal(size=3) * 0.1
    s.q = quat_from_euler(0.1, -0.08, 0.6)
    uv = np.column_stack([rng.uniform(50, 600, n_landmarks), rng.uniform(50, 440, n_landmarks)])
    y, _, _ = initial_landmarks(s.p - np.array([0.05, 0.02, 0.0]), s.R, CAMERA, R_BC, T_BC, uv, rng.uniform(0.8, 2.0, n_landmarks))
    s.landmarks = y
    n = s.robot_dim + 6 * n_landmarks
    A = rng.normal(size=(n, n)) * 0.02
    s.cov = A @ A.T + 1e-4 * np.eye(n)
    return s


def perturbed(state: FilterState, dx: np.ndarray) -> FilterState:
    """The state moved by an error-state vector ``[δp, δθ, δy...]`` (robot pose and landmarks only)."""
    t = state.copy()
    t.p = t.p + dx[0:3]
    t.q = quat_mul(quat_exp(dx[3:6]), t.q)
    t.landmarks = t.landmarks + dx[6:].reshape(-1, 6)
    return t


def test_down_is_theta_phi_zero_and_angles_invert_direction():
    np.testing.assert_allclose(direction(0.0, 0.0), [0.0, 0.0, 1.0])
    np.testing.assert_allclose(direction(np.pi / 2, 0.0), [0.0, 1.0, 0.0], atol=1e-15)  # east
    np.testing.assert_allclose(direction(0.0, -np.pi / 2), [1.0, 0.0, 0.0], atol=1e-15)  # north
    rng = np.random.default_rng(0)
    theta, phi = rng.uniform(-1.4, 1.4, 50), rng.uniform(-1.4, 1.4, 50)
    t2, p2 = angles(3.0 * direction(theta, phi))
    np.testing.assert_allclose(t2, theta)
    np.testing.assert_allclose(p2, phi)
    m = direction(theta, phi)
    J = angles_jacobian(m)
    h = 1e-7
    for i in range(3):
        d = np.zeros(3)
        d[i] = h
        num = (np.stack(angles(m + d), -1) - np.stack(angles(m - d), -1)) / (2 * h)
        np.testing.assert_allclose(J[:, :, i], num, atol=1e-6)


def test_landmark_point_round_trip_and_jacobian():
    s = make_state()
    P = landmark_points(s.landmarks)
    # The point seen from its anchor along its ray at depth 1/ρ.
    dist = np.linalg.norm(P - s.landmarks[:, :3], axis=1)
    np.testing.assert_allclose(dist, 1.0 / s.landmarks[:, 5])
    J = point_jacobian(s.landmarks)
    h = 1e-7
    for i in range(6):
        d = np.zeros(6)
        d[i] = h
        num = (landmark_points(s.landmarks + d) - landmark_points(s.landmarks - d)) / (2 * h)
        np.testing.assert_allclose(J[:, :, i], num, atol=1e-6)


@pytest.mark.parametrize("variant", ["thesis", "biases"])
def test_measurement_jacobians_match_central_differences(variant):
    s = make_state(variant)
    pred = predict(s, CAMERA, R_BC, T_BC, 1.0)
    m = s.n_landmarks
    dim = 6 + 6 * m
    h = 1e-7
    numeric = np.zeros((m, 2, dim))
    for i in range(dim):
        d = np.zeros(dim)
        d[i] = h
        plus = predict(perturbed(s, d), CAMERA, R_BC, T_BC, 1.0).uv
        minus = predict(perturbed(s, -d), CAMERA, R_BC, T_BC, 1.0).uv
        numeric[:, :, i] = (plus - minus) / (2 * h)
    assert pred.in_image.all()
    for j in range(m):
        np.testing.assert_allclose(pred.H_pose[j], numeric[j, :, 0:6], rtol=1e-5, atol=1e-3)
        np.testing.assert_allclose(pred.H_landmark[j], numeric[j, :, 6 + 6 * j : 12 + 6 * j], rtol=1e-5, atol=1e-3)
        others = np.delete(numeric[j, :, 6:], np.s_[6 * j : 6 * j + 6], axis=1)
        assert np.abs(others).max() < 1e-6  # a landmark's pixel depends on nothing else


def test_prediction_at_infinity_is_the_bearing():
    s = make_state(n_landmarks=1)
    s.landmarks[0, 5] = 0.0  # ρ = 0: a point at infinity stays well defined
    h_c, h_w, _, _ = predict_h(s, R_BC, T_BC)
    np.testing.assert_allclose(h_w[0], direction(*s.landmarks[0, 3:5]))
    assert np.isfinite(predict(s, CAMERA, R_BC, T_BC, 1.0).uv).all()


def test_innovation_covariance_equals_full_h_p_ht():
    s = make_state(n_landmarks=3)
    pred = predict(s, CAMERA, R_BC, T_BC, 0.7)
    for j in range(3):
        H = np.zeros((2, s.dim))
        H[:, ROBOT_POSE_COLS] = pred.H_pose[j]
        H[:, s.landmark_slice(j)] = pred.H_landmark[j]
        np.testing.assert_allclose(pred.S[j], H @ s.cov @ H.T + 0.49 * np.eye(2), rtol=1e-10, atol=1e-12)


def test_initialisation_jacobians_match_central_differences():
    s = make_state(n_landmarks=0)
    uv = np.array([[40.0, 30.0], [327.5, 246.5], [610.0, 470.0]])
    rho = np.array([0.5, 1.2, 3.0])
    y, J_x, J_z = initial_landmarks(s.p, s.R, CAMERA, R_BC, T_BC, uv, rho)
    h = 1e-6
    for i in range(6):
        d = np.zeros(6)
        d[i] = h
        sp, sm = perturbed(s, d), perturbed(s, -d)
        yp = initial_landmarks(sp.p, sp.R, CAMERA, R_BC, T_BC, uv, rho)[0]
        ym = initial_landmarks(sm.p, sm.R, CAMERA, R_BC, T_BC, uv, rho)[0]
        np.testing.assert_allclose(J_x[:, :, i], (yp - ym) / (2 * h), atol=1e-7)
    for i in range(3):
        d = np.zeros(3)
        d[i] = 1e-4 if i < 2 else h
        yp = initial_landmarks(s.p, s.R, CAMERA, R_BC, T_BC, uv + d[:2], rho + d[2])[0]
        ym = initial_landmarks(s.p, s.R, CAMERA, R_BC, T_BC, uv - d[:2], rho - d[2])[0]
        np.testing.assert_allclose(J_z[:, :, i], (yp - ym) / (2 * d[i]), atol=1e-8)
    # The new landmark re-projects onto the pixel it came from.
    t = s.copy()
    t.landmarks = y
    t.cov = np.eye(t.robot_dim + 18) * 1e-4
    np.testing.assert_allclose(predict(t, CAMERA, R_BC, T_BC, 1.0).uv, uv, atol=1e-8)


def test_new_landmark_covariance_is_first_order_with_cross_covariance():
    s = make_state(n_landmarks=2, seed=4)
    old = s.cov.copy()
    uv = np.array([[100.0, 100.0], [500.0, 300.0]])
    y, J_x, J_z = initial_landmarks(s.p, s.R, CAMERA, R_BC, T_BC, uv, np.array([1.0, 1.0]))
    R_z = np.array([np.diag([1.0, 1.0, 0.25])] * 2)
    add_landmarks(s, y, J_x, J_z, R_z)
    n = old.shape[0]
    assert s.cov.shape == (n + 12, n + 12) and s.n_landmarks == 4
    np.testing.assert_array_equal(s.cov[:n, :n], old)
    # Full first-order propagation through x_new = [x; g(x_pose, z)].
    G = np.zeros((n + 12, n))
    G[:n] = np.eye(n)
    G[n:, ROBOT_POSE_COLS] = J_x.reshape(12, 6)
    Gz = np.zeros((n + 12, 6))
    Gz[n : n + 6, 0:3] = J_z[0]
    Gz[n + 6 :, 3:6] = J_z[1]
    expected = G @ old @ G.T + Gz @ np.kron(np.eye(2), R_z[0]) @ Gz.T
    np.testing.assert_allclose(s.cov, expected, atol=1e-14)
    np.testing.assert_allclose(s.cov[n:, :n], J_x.reshape(12, 6) @ old[ROBOT_POSE_COLS, :], atol=1e-15)  # P_yx = J_x P_x·
    assert np.all(np.linalg.eigvalsh(s.cov) > -1e-12)


def test_remove_landmarks_drops_their_rows_and_columns():
    s = make_state(n_landmarks=4, seed=5)
    old = s.copy()
    remove_landmarks(s, np.array([False, True, False, True]))
    keep = np.r_[0 : s.robot_dim, old.landmark_slice(0), old.landmark_slice(2)]
    np.testing.assert_array_equal(s.cov, old.cov[np.ix_(keep, keep)])
    np.testing.assert_array_equal(s.landmarks, old.landmarks[[0, 2]])
    remove_landmarks(s, np.zeros(2, dtype=bool))
    assert s.n_landmarks == 2


def test_stacked_update_reduces_uncertainty_and_moves_toward_measurements():
    s = make_state(n_landmarks=4, seed=6)
    pred = predict(s, CAMERA, R_BC, T_BC, 1.0)
    measured = pred.uv[[0, 2]] + np.array([[1.5, -1.0], [-0.5, 2.0]])
    before = s.cov.copy()
    out = stacked_update(s, pred, np.array([0, 2]), measured, 1.0)
    assert out.accepted and out.dof == 4
    after = predict(s, CAMERA, R_BC, T_BC, 1.0).uv[[0, 2]]
    assert np.linalg.norm(after - measured) < np.linalg.norm(pred.uv[[0, 2]] - measured)
    assert np.trace(s.cov) < np.trace(before)
    assert np.all(np.linalg.eigvalsh(s.cov) > -1e-12)


def test_iterated_update_keeps_a_far_off_depth_guess_consistent():
    """Landmarks born with ρ = 0.1 (10 m) that are really 0.75 m away, seen after a 10 cm move
    that the filter believes was 11.5 ± 2 cm. Depth and baseline trade off (only ρ·b is seen):
    one linearisation at the guess claims a depth it does not have; the iteration does not."""
    s = make_state(n_landmarks=0)
    uv0 = np.array([[300.0, 200.0], [100.0, 100.0], [500.0, 400.0], [550.0, 100.0]])
    y, J_x, J_z = initial_landmarks(s.p, s.R, CAMERA, R_BC, T_BC, uv0, np.full(4, 0.1))
    s.cov = np.eye(s.robot_dim) * 1e-6
    add_landmarks(s, y, J_x, J_z, np.array([np.eye(3)] * 4))
    truth = y.copy()
    truth[:, 5] = 1.0 / 0.75
    seen = s.copy()
    seen.p, seen.landmarks = s.p + np.array([0.1, 0.0, 0.0]), truth
    measured = predict(seen, CAMERA, R_BC, T_BC, 1.0).uv
    s.p = seen.p + np.array([0.015, 0.0, 0.0])
    s.cov[0:3, 0:3] += np.eye(3) * 0.02**2
    once, iterated = s.copy(), s.copy()
    assert stacked_update(once, predict(once, CAMERA, R_BC, T_BC, 1.0), np.arange(4), measured, 1.0).accepted
    assert iterated_update(iterated, CAMERA, R_BC, T_BC, np.arange(4), measured, 1.0, iterations=6).accepted
    rho = s.robot_dim + 6 * np.arange(4) + 5

    def sigmas_off(state: FilterState) -> np.ndarray:
        return np.abs(state.landmarks[:, 5] - truth[:, 5]) / np.sqrt(state.cov[rho, rho])

    assert np.all(sigmas_off(once) > 3.0)  # overconfident
    assert np.all(sigmas_off(iterated) < 3.0)
    np.testing.assert_allclose(predict(iterated, CAMERA, R_BC, T_BC, 1.0).uv, measured, atol=0.5)


def test_the_camera_is_blind_to_a_shift_and_a_turn_about_down_and_the_iterated_update_stays_blind():
    """The four directions are those the measurement does not change: moved along each, every predicted pixel
    stays (central differences, not the analytic Jacobian). After an iterated update relinearised away from
    the prior, the heading gained no information: the information along the turn, carried to the new
    estimate, is what it was along the turn at the prior."""
    s = make_state(n_landmarks=5, seed=3)
    idx = np.arange(5)
    N = unobservable_directions(s, idx)
    base = predict(s, CAMERA, R_BC, T_BC, 1.0).uv
    for k in range(4):
        moved = [predict(perturbed(s, sign * 1e-6 * N[:, k]), CAMERA, R_BC, T_BC, 1.0).uv for sign in (1.0, -1.0)]
        assert np.abs(moved[0] - moved[1]).max() / 2e-6 < 1e-3, k  # pixels per unit move: none
    assert np.abs(N[:, 3] @ N[:, 3]) > 1.0  # the turn moves the landmarks' angles, not only the heading
    pred = predict(s, CAMERA, R_BC, T_BC, 1.0)
    cols, H = _stacked_jacobian(s, idx, pred.H_pose[idx], pred.H_landmark[idx])
    np.testing.assert_allclose(observability_constrained(H, N), H, atol=1e-9 * np.abs(H).max())  # blind already here
    far = s.copy()
    measured = base + np.random.default_rng(1).normal(0.0, 3.0, base.shape)
    assert iterated_update(far, CAMERA, R_BC, T_BC, idx, measured, 1.0, iterations=5).accepted
    turn = np.zeros(s.dim)
    turn[cols] = N[:, 3]
    info_before = turn @ np.linalg.solve(s.cov, turn)
    carried = turn + heading_gauge(far) - heading_gauge(s)  # the turn at the new estimate (covariance.transfer_gauge)
    info_after = carried @ np.linalg.solve(far.cov, carried)
    assert info_after == pytest.approx(info_before, rel=1e-6)


def _hover_over_floor(rng: np.random.Generator, k: int = 20) -> FilterState:
    """A vehicle 1.2 m over a floor, heading sigma 2°, its map of ``k`` landmarks started from its pose."""
    s = FilterState(StateLayout("biases"))
    s.p, s.q = np.array([0.0, 0.0, -1.2]), quat_from_euler(0.01, -0.02, 0.3)
    sigmas = [0.02] * 3 + [0.01] * 3 + [np.radians(1.0)] * 2 + [np.radians(2.0)] + [1e-3] * 3 + [0.02] * 3
    s.cov = np.diag(np.square(sigmas))
    uv = np.column_stack([rng.uniform(40, 616, k), rng.uniform(40, 454, k)])
    rays, _ = world_rays(s.R, R_BC, CAMERA, uv)
    rho = rays[:, 2] / np.linalg.norm(rays, axis=1) / -(s.p + s.R @ T_BC)[2]  # the floor at down = 0
    y, J_x, J_z = initial_landmarks(s.p, s.R, CAMERA, R_BC, T_BC, uv, rho)
    R_z = np.zeros((k, 3, 3))
    R_z[:, 0, 0] = R_z[:, 1, 1] = 1.0
    R_z[:, 2, 2] = (0.3 * rho) ** 2
    add_landmarks(s, y, J_x, J_z, R_z)
    return s


def test_a_hover_seen_again_and_again_gives_no_heading():
    """A hovering vehicle's map matched in 150 frames with pixel noise: each update moves the landmarks and the
    pose a little, and the turn the camera is blind to moves with them. Unless the covariance follows it
    (covariance.transfer_gauge), every next update reads heading out of the mismatch: the heading sigma fell
    from 2° to 0.8° here, where nothing showed the heading (the hover's Test 3: 2° to 0.87° in 20 s)."""
    rng = np.random.default_rng(4)
    s = _hover_over_floor(rng)
    truth = predict(s, CAMERA, R_BC, T_BC, 1.0).uv
    idx = np.arange(s.n_landmarks)
    for _ in range(150):
        measured = truth + rng.normal(0.0, 1.0, truth.shape)
        assert stacked_update(s, predict(s, CAMERA, R_BC, T_BC, 1.0), idx, measured, 1.0).accepted
    assert np.degrees(np.sqrt(s.cov[8, 8])) == pytest.approx(2.0, rel=1e-3)


def test_a_gps_fix_at_the_vehicle_leaves_the_heading_gauge_where_the_fix_moved_it():
    """A fix at the vehicle (no lever arm) is blind to a turn of the vehicle and its map about the vehicle, but
    it moves the pose, velocity and map through their correlations, and the turn moves with them: carried
    (carry_gauge, as the filter calls it after a fix), the information along the turn at the new estimate is
    what it was along the turn at the old one. Without it the camera's next update, blind to the turn at its
    own estimate, reads heading out of the move (the hover's Test 3: heading sigma 1.77° at 20 s, 1.92° with it)."""
    s = make_state(n_landmarks=5, seed=8)
    before = heading_gauge(s)
    info_before = before @ np.linalg.solve(s.cov, before)
    moved = s.copy()
    assert GpsUpdater(np.zeros(3), None).update(moved, GpsFix(0, s.p + np.array([0.03, -0.02, 0.01]), 0.02, 0.02)).accepted
    after = heading_gauge(moved)
    assert np.abs(after - before).max() > 1e-3  # the fix moved the turn
    uncarried = after @ np.linalg.solve(moved.cov, after)
    carry_gauge(moved, before)
    assert after @ np.linalg.solve(moved.cov, after) == pytest.approx(info_before, rel=1e-6)
    assert abs(uncarried / info_before - 1.0) > 1e-3


def test_stacked_jacobian_puts_each_landmark_block_on_its_own_rows_and_columns():
    s = make_state(n_landmarks=7, seed=3)
    pred = predict(s, CAMERA, R_BC, T_BC, 1.0)
    idx = np.array([5, 1, 3])
    cols, H = _stacked_jacobian(s, idx, pred.H_pose[idx], pred.H_landmark[idx])
    assert H.shape == (6, 6 + 6 * 3)
    for j, i in enumerate(idx):
        rows = slice(2 * j, 2 * j + 2)
        np.testing.assert_array_equal(H[rows, :6], pred.H_pose[i])
        np.testing.assert_array_equal(H[rows, 6 + 6 * j : 12 + 6 * j], pred.H_landmark[i])
        np.testing.assert_array_equal(cols[6 + 6 * j : 12 + 6 * j], s.robot_dim + 6 * i + np.arange(6))
        others = np.delete(H[rows, 6:], np.s_[6 * j : 6 * j + 6], axis=1)
        assert not others.any()
    # Only the matched landmarks projected: the same numbers as projecting all and picking.
    np.testing.assert_array_equal(predict_h(s, R_BC, T_BC, idx)[0], predict_h(s, R_BC, T_BC)[0][idx])


def test_a_guessed_depth_without_a_baseline_still_shows_a_tilt_drift():
    """Matches of landmarks whose depth is still a guess, the camera where it started them: a turn moves every
    bearing alike whatever the depth, so they show the attitude (and through it the gyro bias), only not the
    depth nor what a misread displacement would take (the accelerometer bias). Held, a hover's gyro-bias
    error from its still window (0.0044 rad/s) drifted the tilt 0.24 -> 0.67° unseen in 2 s, its gravity
    leak grew a velocity error 4 sigma off, and the first baseline read it as parallax (Test 2: 32 m)."""
    rng = np.random.default_rng(6)
    s = _hover_over_floor(rng)
    s.landmarks[:, 5] = 0.1  # Civera's guess: the floor is really 1.2 m down
    s.cov[s.robot_dim + 5 :: 6, s.robot_dim + 5 :: 6] += np.eye(s.n_landmarks) * 1.0
    s.cov[6:8, 6:8] += np.eye(2) * np.radians(0.6) ** 2  # what the tilt grew since the map's start, unshared
    truth = s.copy()
    s.q = quat_mul(quat_exp(np.radians([0.5, -0.4, 0.0])), s.q)  # and the estimate's tilt drifted so
    measured = predict(truth, CAMERA, R_BC, T_BC, 1.0).uv
    idx = np.arange(s.n_landmarks)
    for _ in range(5):
        hold = CameraPipeline._no_baseline_held(s, idx)
        assert iterated_update(s, CAMERA, R_BC, T_BC, idx, measured + rng.normal(0.0, 1.0, measured.shape), 1.0,
                               hold, 1).accepted
    assert np.degrees(np.linalg.norm(quat_log(quat_mul(truth.q, quat_conj(s.q)))[0:2])) < 0.15
    np.testing.assert_array_equal(s.landmarks[:, 5], 0.1)  # the depth still held


def test_the_turn_about_down_is_numpys_cross_product_to_the_bit():
    """The gauges' ``[0, 0, 1] × x`` makes the products and differences ``np.cross`` makes: the same bits for
    signed zeros, infinities and NaN too, one vector or a stack."""
    from vtolpose.estimator.vision.camera_update import _DOWN, _down_cross

    rng = np.random.default_rng(4)
    x = rng.normal(size=(200, 3))
    x[::7, 1], x[::5, 0], x[::3, 2] = 0.0, -0.0, -0.0
    x[::11, 2], x[::13, 0] = np.inf, np.nan
    with np.errstate(invalid="ignore"):
        for given in (x, x[0], x[1], x[7]):
            expected, got = np.cross(_DOWN, given), _down_cross(given)
            assert got.shape == expected.shape
            np.testing.assert_array_equal(got, expected)
            np.testing.assert_array_equal(np.signbit(got), np.signbit(expected))


@pytest.mark.parametrize("calibration_states", [0, 1])
def test_the_gauges_are_their_definitions_built_element_by_element(calibration_states):
    """The heading gauge and the four unobservable directions, written into views of their vectors, equal the
    same directions built one landmark at a time with ``np.cross`` and the angles' Jacobian, bit for bit."""
    from vtolpose.estimator.core.covariance import YAW

    s = make_state(n_landmarks=6, seed=11)
    if calibration_states:
        s.calib = np.zeros(1)
        n = s.map_start + 6 * s.n_landmarks
        A = np.random.default_rng(2).normal(size=(n, n)) * 0.02
        s.cov = A @ A.T + 1e-4 * np.eye(n)
    down = np.array([0.0, 0.0, 1.0])
    gauge = heading_gauge(s)
    expected = np.zeros(s.dim)
    expected[s.layout.V] = np.cross(down, s.v)
    expected[YAW] = 1.0
    for j, y in enumerate(s.landmarks):
        m = direction(y[3], y[4])
        row = s.map_start + 6 * j
        expected[row : row + 3] = np.cross(down, y[0:3] - s.p)
        expected[row + 3 : row + 5] = np.einsum("ij,j->i", angles_jacobian(m[None])[0], np.cross(down, m[None])[0])
    np.testing.assert_array_equal(gauge, expected)

    idx = np.array([4, 0, 2])
    N = unobservable_directions(s, idx)
    r = 6 + s.calib.shape[0]
    assert N.shape == (r + 6 * len(idx), 4)
    expected = np.zeros_like(N)
    expected[0:3, 0:3] = np.eye(3)
    expected[0:3, 3] = np.cross(down, s.p)
    expected[3:6, 3] = down
    for j, i in enumerate(idx):
        y = s.landmarks[i]
        m = direction(y[3], y[4])
        row = r + 6 * j
        expected[row : row + 3, 0:3] = np.eye(3)
        expected[row : row + 3, 3] = np.cross(down, y[0:3])
        expected[row + 3 : row + 5, 3] = np.einsum("ij,j->i", angles_jacobian(m[None])[0], np.cross(down, m[None])[0])
    np.testing.assert_array_equal(N, expected)
