"""A camera wider than the working width is seen reduced to it: frames, features and intrinsics together."""

from __future__ import annotations

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2", reason="feature extraction needs OpenCV")

from vtolpose.estimator.core.calibration import Calibration, CameraCalibration, ImuCalibration, ImuNoise, working_size  # noqa: E402
from vtolpose.estimator.filter import Estimator, FilterOptions  # noqa: E402
from vtolpose.estimator.vision.camera_model import CameraModel  # noqa: E402
from vtolpose.estimator.vision.camera_pipeline import CameraOptions  # noqa: E402
from vtolpose.estimator.vision.feature_tracker import FrameExtractor  # noqa: E402
from vtolpose.estimator.vision.features import FeatureOptions, extract_features  # noqa: E402

WIDE = CameraCalibration(1280, 720, 910.0, 905.0, 641.3, 352.8, np.array([-0.1, 0.03, 4e-4, -2e-4, 0.0]))


def textured(seed: int, shape: tuple[int, int]) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = rng.normal(size=(shape[0] // 8, shape[1] // 8)).astype(np.float32)
    img = cv2.resize(noise, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    return np.clip(128 + 40 * img / img.std(), 0, 255).astype(np.uint8)


def test_the_working_camera_sees_each_ray_where_the_reduced_frame_has_it() -> None:
    assert working_size(1280, 720, 640) == (640, 360) and working_size(656, 494, 640) == (640, 482)
    assert working_size(640, 360, 640) == (640, 360) and working_size(1280, 720, 0) == (1280, 720)
    small = WIDE.working(640)
    assert (small.width, small.height) == (640, 360) and WIDE.working(0) is WIDE and WIDE.working(2000) is WIDE
    rays = np.column_stack([np.random.default_rng(1).uniform(-0.5, 0.5, (50, 2)), np.ones(50)])
    full = CameraModel(WIDE).project_jacobian(rays)[0]
    reduced = CameraModel(small).project_jacobian(rays)[0]
    # A pixel of the reduced frame covers two of the full one: centre x' + 1/2 = (x + 1/2) / 2.
    np.testing.assert_allclose(reduced, (full + 0.5) * 0.5 - 0.5, atol=1e-9)


def test_the_extractor_reduces_a_wide_frame_and_still_refuses_a_wrong_one() -> None:
    extract = FrameExtractor(FeatureOptions(working_width=640), (720, 1280))
    features = extract(textured(2, (720, 1280)), 1_000)
    assert features.problem is None and features.image_shape == (360, 640) and len(features) > 50
    assert features.keypoints[:, 0].max() < 640 and features.keypoints[:, 1].max() < 360
    assert extract(textured(3, (480, 640)), 2_000).problem == "wrong_size"
    as_is = FrameExtractor(FeatureOptions(working_width=0), (720, 1280))(textured(2, (720, 1280)), 3_000)
    assert as_is.image_shape == (720, 1280)
    # The same from extract_features called alone, and through the optical-flow tracker.
    direct = extract_features(textured(2, (720, 1280)), 4_000, FeatureOptions(working_width=640), (720, 1280))
    assert direct.image_shape == (360, 640) and np.array_equal(direct.keypoints, features.keypoints)
    tracked = FrameExtractor(FeatureOptions(working_width=640, track_between=2), (720, 1280))
    assert all(tracked(textured(2, (720, 1280)), t).image_shape == (360, 640) for t in (5_000, 6_000, 7_000))


def test_the_estimator_takes_the_reduced_frames_of_a_wide_camera() -> None:
    noise = ImuNoise.isotropic(3e-4, 2e-5, 2e-3, 3e-4)
    est = Estimator(Calibration(imu=ImuCalibration(125.0, noise), camera=WIDE, initial_heading_rad=0.3),
                    FilterOptions(camera=CameraOptions(working_width=640)))
    for k in range(320):  # 2.5 s at rest: the static start
        est.process_imu(1_000_000_000 + k * 8_000_000, np.zeros(3), np.array([0.0, 0.0, -9.80665]))
    features = FrameExtractor(FeatureOptions(working_width=640), (720, 1280))(textured(4, (720, 1280)), 3_600_000_000)
    report = est.process_features(features)
    assert report.reason != "wrong_size" and est.counts["camera"].rejected.get("wrong_size", 0) == 0
    assert est.camera.calibration.fx == pytest.approx(455.0)
    # Without the working width on the estimator's side the reduced frame is not its camera's: refused, counted.
    other = Estimator(Calibration(imu=ImuCalibration(125.0, noise), camera=WIDE, initial_heading_rad=0.3),
                      FilterOptions(camera=CameraOptions(working_width=0)))
    for k in range(320):
        other.process_imu(1_000_000_000 + k * 8_000_000, np.zeros(3), np.array([0.0, 0.0, -9.80665]))
    assert other.process_features(features).reason == "wrong_size"
