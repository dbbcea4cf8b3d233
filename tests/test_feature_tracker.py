"""Features tracked by optical flow between detections (``features.track_between``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vtolpose.estimator import FeatureOptions, FeatureTracker, extract_features

SHIFT = np.array([3.2, -1.7])


def _texture(seed: int = 3, size: tuple[int, int] = (360, 640)) -> np.ndarray:
    """Smooth random blobs: corners SIFT finds and Lucas–Kanade follows."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, 1.0, size).astype(np.float32)
    image = cv2.GaussianBlur(noise, (0, 0), 3.0)
    image = (image - image.min()) / (image.max() - image.min()) * 200.0 + 30.0
    return image.astype(np.uint8)


def _shifted(image: np.ndarray, shift: np.ndarray) -> np.ndarray:
    M = np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]]])
    return cv2.warpAffine(image, M, (image.shape[1], image.shape[0]), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


def test_tracked_points_follow_the_image_and_keep_their_detections_descriptors():
    tracker = FeatureTracker(FeatureOptions(track_between=4))
    first = _texture()
    detected = tracker.features(first, 1)
    tracked = tracker.features(_shifted(first, SHIFT), 2)
    assert (tracker.detections, tracker.tracked_frames) == (1, 1)
    assert len(tracked) > 0.8 * len(detected)
    # Each tracked point is a detected one moved by the shift, with that point's descriptor and response.
    rows = [int(np.argmin(np.linalg.norm(detected.descriptors - d, axis=1))) for d in tracked.descriptors]
    assert np.array_equal(tracked.descriptors, detected.descriptors[rows])
    assert np.array_equal(tracked.responses, detected.responses[rows])
    moved = tracked.keypoints - detected.keypoints[rows]
    assert np.median(np.linalg.norm(moved - SHIFT, axis=1)) < 0.1


def test_the_last_pairs_motion_guides_the_next_pairs_flow(monkeypatch):
    """A camera that swings faster each frame: 20 px, then 40 px twice. Lucas-Kanade alone loses nearly every
    point past the first pair; from the last pair's image motion it keeps most, where they truly went."""
    from vtolpose.estimator.vision import feature_tracker as tracking

    image = _texture(size=(480, 640))
    direction = np.array([1.0, -0.5])
    frames = [_shifted(image, direction * s) for s in (0.0, 20.0, 60.0, 100.0)]
    kept = {}
    fitted = tracking._image_motion
    for guided in (True, False):
        monkeypatch.setattr(tracking, "_image_motion", fitted if guided else (lambda before, after: None))
        tracker = FeatureTracker(FeatureOptions(track_between=4, min_tracked_fraction=0.0))
        found = [tracker.features(frame, k + 1) for k, frame in enumerate(frames)]
        assert (tracker.detections, tracker.tracked_frames) == (1, 3)
        kept[guided] = [len(f) for f in found]
        if guided:
            rows = [int(np.argmin(np.linalg.norm(found[0].descriptors - d, axis=1))) for d in found[3].descriptors]
            moved = found[3].keypoints - found[0].keypoints[rows]
            assert np.median(np.linalg.norm(moved - 100.0 * direction, axis=1)) < 0.1
    assert kept[True][1] == kept[False][1] > 300  # the first pair has no guess either way
    assert kept[False][3] < 0.1 * kept[False][1]
    assert kept[True][3] > 0.7 * kept[True][1]


def test_a_detection_comes_every_track_between_plus_one_frames():
    tracker = FeatureTracker(FeatureOptions(track_between=2))
    image = _texture()
    for k in range(7):
        tracker.features(_shifted(image, 0.5 * k * SHIFT), k + 1)
    assert (tracker.detections, tracker.tracked_frames) == (3, 4)  # frames 1, 4, 7 detected


def test_points_the_flow_cannot_confirm_are_dropped():
    tracker = FeatureTracker(FeatureOptions(track_between=4))
    first = _texture()
    detected = tracker.features(first, 1)
    covered = _shifted(first, SHIFT)
    covered[:, :320] = _texture(seed=9)[:, :320]  # the left half replaced by another scene
    tracked = tracker.features(covered, 2)
    assert tracker.tracked_frames == 1
    on_right = np.count_nonzero(detected.keypoints[:, 0] > 330)
    assert len(tracked) <= on_right + 0.05 * len(detected)
    assert np.all(tracked.keypoints[:, 0] > 300)


def test_too_few_tracked_points_bring_a_detection_early():
    tracker = FeatureTracker(FeatureOptions(track_between=4, min_tracked_fraction=0.9))
    first = _texture()
    tracker.features(first, 1)
    other = _texture(seed=5)
    other[:, 320:] = _shifted(first, SHIFT)[:, 320:]  # about half the points survive
    again = tracker.features(other, 2)
    assert (tracker.detections, tracker.tracked_frames) == (2, 0)
    assert len(again) == len(extract_features(other, 2, tracker.options))


def test_out_of_order_and_rejected_frames_start_again_from_a_detection():
    tracker = FeatureTracker(FeatureOptions(track_between=4))
    image = _texture()
    tracker.features(image, 10)
    older = tracker.features(_shifted(image, SHIFT), 5)  # out of order: detected, the newer frame kept
    assert (tracker.detections, tracker.tracked_frames) == (1, 0) and len(older) > 0
    tracker.features(_shifted(image, SHIFT), 11)
    assert tracker.tracked_frames == 1
    black = tracker.features(np.zeros_like(image), 12)
    assert black.problem == "black"
    tracker.features(image, 13)
    assert tracker.detections == 2  # the frame after a rejected one is detected, not tracked


def test_options_are_checked():
    with pytest.raises(ValueError, match="track_between"):
        FeatureOptions(track_between=-1)
    with pytest.raises(ValueError, match="min_tracked_fraction"):
        FeatureOptions(min_tracked_fraction=1.5)
    with pytest.raises(ValueError, match="track_between >= 1"):
        FeatureTracker(FeatureOptions())


def test_a_tracking_processor_gets_one_camera_worker():
    from vtolpose.config import load_config
    from vtolpose.estimator.core.calibration import Calibration, ImuCalibration, ImuNoise
    from vtolpose.service.replay.session import FrameProcessor
    from vtolpose.service.runtime.daemon import build_runtime

    cfg = load_config(None, {"replay": {"camera_workers": 4}})
    tracking = FrameProcessor(FeatureOptions(track_between=3), None)
    detecting = FrameProcessor(FeatureOptions(), None)
    assert tracking.in_order and not detecting.in_order
    calibration = Calibration(imu=ImuCalibration(200.0, ImuNoise.isotropic(3e-4, 2e-5, 2e-3, 3e-4)))
    runtimes = [build_runtime(cfg, calibration, camera_processor=p, lockstep=True) for p in (tracking, detecting)]
    assert [r.options.camera_workers for r in runtimes] == [1, 4]
