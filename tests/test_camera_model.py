"""Camera model: projection and undistortion against OpenCV, Jacobians against central differences."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vtolpose.estimator.core.calibration import CameraCalibration
from vtolpose.estimator.vision.camera_model import CameraModel

from conftest import check_lens_jacobians, check_projection_jacobian

DISTORTION = np.array([-0.28, 0.09, 0.0012, -0.0008, -0.01])


def make_camera(distortion: np.ndarray = DISTORTION) -> CameraModel:
    return CameraModel(CameraCalibration(656, 494, 570.0, 572.0, 327.5, 246.5, distortion))


def points(n: int = 200, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.55, 0.55, size=(n, 2))
    z = rng.uniform(0.3, 40.0, size=n)
    return np.column_stack([xy * z[:, None], z])


def test_projection_matches_cv2_project_points():
    cam = make_camera()
    P = points()
    uv, front = cam.project(P)
    ref, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.calibration.K, DISTORTION)
    assert front.all()
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)


def test_undistortion_inverts_projection_and_matches_cv2():
    cam = make_camera()
    rng = np.random.default_rng(1)
    uv = np.column_stack([rng.uniform(0, 655, 300), rng.uniform(0, 493, 300)])
    xn = cam.undistort(uv)
    np.testing.assert_allclose(cam.normalized_to_pixel(xn), uv, atol=1e-8)
    # OpenCV's fixed-point iteration, run to convergence, is the independent reference.
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.calibration.K, DISTORTION, None, None, None, criteria)
    np.testing.assert_allclose(xn, ref.reshape(-1, 2), atol=1e-7)


def test_no_distortion_is_the_plain_pinhole():
    cam = make_camera(np.zeros(5))
    uv = np.array([[10.0, 20.0], [600.0, 480.0]])
    xn = cam.undistort(uv)
    np.testing.assert_allclose(xn[:, 0], (uv[:, 0] - 327.5) / 570.0)
    np.testing.assert_allclose(cam.normalized_to_pixel(xn), uv)


def test_projection_jacobian_matches_central_differences():
    check_projection_jacobian(make_camera(), points(50, seed=2))


def test_distortion_and_undistortion_jacobians():
    check_lens_jacobians(make_camera(), np.random.default_rng(3).uniform(-0.5, 0.5, size=(40, 2)))


def test_points_behind_the_camera_are_flagged_with_nan_pixels():
    cam = make_camera()
    uv, front = cam.project(np.array([[0.1, 0.1, -1.0], [0.0, 0.0, 0.0], [0.1, 0.0, 2.0]]))
    assert front.tolist() == [False, False, True]
    assert np.isnan(uv[:2]).all() and np.isfinite(uv[2]).all()
    assert cam.in_image(uv).tolist() == [False, False, True]


@pytest.mark.parametrize("uv, inside", [((0.0, 0.0), True), ((-1.0, 10.0), False), ((655.4, 493.4), True), ((10.0, 494.0), False)])
def test_in_image(uv, inside):
    assert bool(make_camera().in_image(np.array([uv]))[0]) is inside
