"""The parallax test that decides when a guessed depth may be learnt: a χ²(2) statistic of the match against
the landmark's ray at infinity, blind to where the filter believes the camera has gone."""

from __future__ import annotations

import numpy as np

from vtolpose.estimator.core.calibration import CameraCalibration
from vtolpose.estimator.core.rotation import quat_exp, quat_from_euler, quat_mul, quat_to_rot
from vtolpose.estimator.core.state import FilterState, StateLayout
from vtolpose.estimator.vision.camera_model import CameraModel
from vtolpose.estimator.vision.camera_update import parallax_significance
from vtolpose.estimator.vision.landmarks import add_landmarks, baseline_significance, initial_landmarks

CAMERA = CameraModel(CameraCalibration(640, 480, 500.0, 500.0, 320.0, 240.0, np.array([-0.1, 0.03, 0.0, 0.0, 0.0])))
R_BC = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # camera looking down, as the vehicle's
T_BC = np.zeros(3)  # the camera at the body's origin: a turn of the body is a turn of the camera about its centre
PIXEL_SIGMA = 1.0
ATTITUDE_SIGMA = np.radians(5.0)


def seen(p: np.ndarray, q: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixels of world ``points`` from the body pose (p, q)."""
    R_WC = quat_to_rot(q) @ R_BC
    uv, front, _ = CAMERA.project_jacobian((points - p) @ R_WC)
    assert np.all(front)
    return uv


def anchored(rng: np.random.Generator, n: int = 30) -> tuple[FilterState, np.ndarray, np.ndarray, np.ndarray]:
    """A filter whose attitude is off by a draw from its own 5° sigma, with ``n`` landmarks placed from noisy pixels
    of floor points 0.9–1.6 m away (depths guessed at 1.2 m). Returns the state, the true pose (p, q) and the points."""
    p_true, q_true = np.array([0.0, 0.0, -1.0]), quat_from_euler(0.05, -0.03, 0.4)
    s = FilterState(StateLayout("biases"))
    s.p = p_true.copy()
    s.q = quat_mul(quat_exp(rng.normal(0.0, ATTITUDE_SIGMA, 3)), q_true)
    s.cov = np.diag(np.r_[np.full(3, 0.01**2), np.full(3, 0.1**2), np.full(3, ATTITUDE_SIGMA**2), np.full(6, 1e-6)])
    uv_true = np.column_stack([rng.uniform(60, 580, n), rng.uniform(60, 420, n)])
    rays_c = np.column_stack([CAMERA.undistort(uv_true), np.ones(n)])
    points = p_true + rng.uniform(0.9, 1.6, (n, 1)) * rays_c @ (quat_to_rot(q_true) @ R_BC).T
    uv = seen(p_true, q_true, points) + rng.normal(0.0, PIXEL_SIGMA, (n, 2))
    y, J_x, J_z = initial_landmarks(s.p, s.R, CAMERA, R_BC, T_BC, uv, np.full(n, 1 / 1.2))
    R_z = np.zeros((n, 3, 3))
    R_z[:, 0, 0] = R_z[:, 1, 1] = PIXEL_SIGMA**2
    R_z[:, 2, 2] = 0.5**2
    add_landmarks(s, y, J_x, J_z, R_z)
    return s, p_true, q_true, points


def turned(s: FilterState, q_true: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """Turn the vehicle by ``turn`` about its own axes, as a gyro without error sees it (the estimate turns with it,
    its error stays what it was); returns the new true attitude."""
    step = quat_exp(turn)
    s.q = quat_mul(s.q, step)
    return quat_mul(q_true, step)


def test_a_turn_without_translation_scores_as_chi2_with_two_degrees_of_freedom() -> None:
    # The attitude error (5°) moves every ray far more than a pixel; it cancels because the rays were placed with the
    # same error, and only the covariance's correlation between them says so. Two pixels' noise is what is left.
    rng = np.random.default_rng(3)
    values = []
    for _ in range(40):
        s, p_true, q_true, points = anchored(rng)
        q_now = turned(s, q_true, np.radians([3.0, -2.0, 8.0]))
        uv = seen(p_true, q_now, points) + rng.normal(0.0, PIXEL_SIGMA, (len(points), 2))
        values.append(parallax_significance(s, CAMERA, R_BC, T_BC, np.arange(len(points)), uv, PIXEL_SIGMA))
    values = np.concatenate(values)
    assert 1.8 < values.mean() < 2.2  # χ²(2): mean 2 (1200 draws: standard error 0.06)
    assert 0.93 < np.mean(values < 5.99) < 0.97  # its 95 % point


def test_a_translation_seen_against_near_points_is_parallax() -> None:
    rng = np.random.default_rng(4)
    s, p_true, q_true, points = anchored(rng)
    moved = p_true + np.array([0.06, 0.08, 0.0])  # 10 cm across the rays, points about 1.2 m away: about 40 px
    uv = seen(moved, q_true, points) + rng.normal(0.0, PIXEL_SIGMA, (len(points), 2))
    values = parallax_significance(s, CAMERA, R_BC, T_BC, np.arange(len(points)), uv, PIXEL_SIGMA)
    assert np.median(values) > 100.0


def test_a_baseline_that_is_only_the_filters_drift_shows_no_parallax() -> None:
    # The vehicle has not moved, the estimate has drifted 10 cm at a claimed sigma of 1 cm: by the estimate's own
    # displacement every landmark has a baseline, by the image none has.
    rng = np.random.default_rng(5)
    s, p_true, q_true, points = anchored(rng)
    s.p = s.p + np.array([0.1, 0.0, 0.0])
    uv = seen(p_true, q_true, points) + rng.normal(0.0, PIXEL_SIGMA, (len(points), 2))
    rows = np.arange(len(points))
    assert np.all(baseline_significance(s, rows, T_BC) > 9.0)
    assert np.mean(parallax_significance(s, CAMERA, R_BC, T_BC, rows, uv, PIXEL_SIGMA) < 9.0) > 0.95
