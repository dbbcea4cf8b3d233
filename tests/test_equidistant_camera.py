"""Equidistant (Kannala–Brandt) lens: against cv2.fisheye, its inverse, its Jacobians, and dataset.yaml."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vtolpose.drivers.files.calibration_yaml import CalibrationError, calibration_from_yaml, calibration_to_yaml
from vtolpose.estimator.core.calibration import Calibration, CameraCalibration, ImuCalibration, ImuNoise
from vtolpose.estimator.vision.camera_model import CameraModel

from conftest import check_lens_jacobians, check_projection_jacobian

COEFFS = np.array([0.02, -0.01, 0.003, -0.0005])


def make_fisheye(coeffs: np.ndarray = COEFFS) -> CameraModel:
    return CameraModel(CameraCalibration(640, 360, 300.0, 301.0, 319.5, 179.5, coeffs, model="equidistant"))


def points(n: int = 200, seed: int = 0, half_angle: float = 1.15) -> np.ndarray:
    """Points in front of the camera up to ``half_angle`` [rad] off its axis, 0.3–40 m away."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0.0, half_angle, n)
    phi = rng.uniform(-np.pi, np.pi, n)
    dist = rng.uniform(0.3, 40.0, n)
    return dist[:, None] * np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])


def test_projection_matches_cv2_fisheye():
    cam = make_fisheye()
    P = points()
    uv, front = cam.project(P)
    ref, _ = cv2.fisheye.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.calibration.K, COEFFS)
    assert front.all()
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)


def test_undistortion_inverts_projection_and_matches_cv2_fisheye():
    cam = make_fisheye()
    P = points(300, seed=1)
    uv = cam.project(P)[0]
    xn = cam.undistort(uv)
    np.testing.assert_allclose(xn, P[:, :2] / P[:, 2:], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(cam.normalized_to_pixel(xn), uv, atol=1e-8)
    ref = cv2.fisheye.undistortPoints(uv.reshape(-1, 1, 2), cam.calibration.K, COEFFS).reshape(-1, 2)
    np.testing.assert_allclose(xn, ref, rtol=1e-6, atol=1e-7)


def test_the_centre_pixel_and_zero_coefficients():
    cam = make_fisheye()
    np.testing.assert_allclose(cam.undistort(np.array([[319.5, 179.5]])), [[0.0, 0.0]])
    np.testing.assert_allclose(cam.distort_jacobian(np.zeros((1, 2)))[0], np.eye(2))
    plain = make_fisheye(np.zeros(4))  # θ_d = θ: the ideal equidistant lens
    xn = np.array([[1.0, 0.0]])
    np.testing.assert_allclose(plain.distort(xn), [[np.pi / 4, 0.0]])


def test_projection_jacobian_matches_central_differences():
    check_projection_jacobian(make_fisheye(), points(60, seed=2))


def test_distortion_and_undistortion_jacobians():
    xn = np.random.default_rng(3).uniform(-1.5, 1.5, size=(40, 2))
    xn[0] = [1e-10, -2e-10]  # the series branch at the optical axis
    check_lens_jacobians(make_fisheye(), xn, undistort_rtol=1e-6)


def test_calibration_checks_the_model_and_its_coefficient_count():
    assert CameraCalibration(640, 360, 300.0, 300.0, 320.0, 180.0, model="equidistant").distortion.tolist() == [0.0] * 4
    assert CameraCalibration(640, 360, 300.0, 300.0, 320.0, 180.0).distortion.tolist() == [0.0] * 5
    with pytest.raises(ValueError, match="4 distortion coefficients"):
        CameraCalibration(640, 360, 300.0, 300.0, 320.0, 180.0, np.zeros(5), model="equidistant")
    with pytest.raises(ValueError, match="camera model"):
        CameraCalibration(640, 360, 300.0, 300.0, 320.0, 180.0, model="kb8")


def _with_camera(camera: CameraCalibration) -> Calibration:
    return Calibration(imu=ImuCalibration(200.0, ImuNoise.isotropic(1e-4, 1e-5, 1e-3, 1e-4)), camera=camera)


def test_dataset_yaml_carries_the_model():
    fisheye = CameraCalibration(640, 360, 300.0, 301.0, 319.5, 179.5, COEFFS, model="equidistant")
    doc = calibration_to_yaml(_with_camera(fisheye))
    assert doc["camera"]["model"] == "equidistant" and len(doc["camera"]["distortion"]) == 4
    back = calibration_from_yaml(doc).camera
    assert back.model == "equidistant"
    np.testing.assert_array_equal(back.distortion, COEFFS)
    radtan = calibration_to_yaml(_with_camera(CameraCalibration(640, 360, 300.0, 300.0, 320.0, 180.0)))
    assert "model" not in radtan["camera"]  # files of radial-tangential cameras stay as they were
    assert calibration_from_yaml(radtan).camera.model == "radtan"


@pytest.mark.parametrize("model, distortion, message", [("fisheye", [0.0] * 4, "camera.model"),
                                                         ("equidistant", [0.0] * 5, "camera.distortion")])
def test_dataset_yaml_refuses_an_unknown_model_or_a_wrong_count(model, distortion, message):
    doc = calibration_to_yaml(_with_camera(CameraCalibration(640, 360, 300.0, 300.0, 320.0, 180.0)))
    doc["camera"].update(model=model, distortion=distortion)
    with pytest.raises(CalibrationError, match=message):
        calibration_from_yaml(doc)
