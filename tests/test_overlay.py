"""Overlay pictures: readable under the gates, a key to the colours, time-ordered names, small files."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from vtolpose.estimator.vision.camera_pipeline import FrameReport
from vtolpose.estimator.vision.features import FrameFeatures
from vtolpose.service.replay.overlay import CYAN, GATE_ALPHA, GREEN, LEGEND, MAGENTA, OverlayWriter, draw_overlay

H, W = 494, 656


def textured_frame(seed: int = 3) -> np.ndarray:
    """A grey frame with photo-like texture (blurred noise), the hard case for file size."""
    noise = np.random.default_rng(seed).uniform(0, 255, (H, W)).astype(np.float32)
    return np.clip(cv2.GaussianBlur(noise, (0, 0), 1.5) * 1.6 - 80, 0, 255).astype(np.uint8)


def frame_and_report(t_ns: int, n_landmarks: int = 40) -> tuple[FrameFeatures, FrameReport]:
    rng = np.random.default_rng(t_ns % 1000)
    keypoints = np.column_stack([rng.uniform(20, W - 20, 300), rng.uniform(30, H - 30, 300)])
    features = FrameFeatures(t_ns, keypoints, np.zeros((300, 128), np.float32), np.ones(300), (H, W))
    ids = np.arange(n_landmarks)
    predicted = keypoints[:n_landmarks] + rng.normal(0, 3, (n_landmarks, 2))
    report = FrameReport(t_ns, True, n_features=300, n_landmarks=n_landmarks, predicted_ids=ids, predicted_uv=predicted,
                         gate_px=100.0, matched_ids=ids[:30], matched_features=np.arange(30), candidates=n_landmarks,
                         new_ids=np.arange(100, 105), new_features=np.arange(200, 205))
    return features, report


def test_names_sort_in_time_order(tmp_path: Path):
    writer = OverlayWriter(tmp_path)
    image = textured_frame()
    for t_ns in (9_999_999_999, 10_000_000_000, 1_403_715_273_262_142_976):
        writer(image, *frame_and_report(t_ns))
    names = [p.name for p in sorted(tmp_path.iterdir())]
    assert [int(n.split(".")[0]) for n in names] == [9_999_999_999, 10_000_000_000, 1_403_715_273_262_142_976]
    assert writer.written == 3


def test_a_frame_with_sixty_gates_stays_small(tmp_path: Path):
    image = textured_frame()
    features, report = frame_and_report(10**9, n_landmarks=60)
    OverlayWriter(tmp_path)(image, features, report)
    (path,) = tmp_path.iterdir()
    ok, png = cv2.imencode(".png", draw_overlay(image, features, report), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    assert ok and path.stat().st_size < 0.4 * len(png)  # at the lightest compression, a ~470 KB PNG
    assert path.stat().st_size < 200_000
    assert cv2.imread(str(path)).shape == (H, W, 3)


def test_gates_are_blended_not_painted_over_the_image():
    image = np.full((H, W), 128, np.uint8)
    features = FrameFeatures(1, np.zeros((0, 2)), np.zeros((0, 128), np.float32), np.zeros(0), (H, W))
    report = FrameReport(1, True, predicted_ids=np.array([7]), predicted_uv=np.array([[300.0, 250.0]]), gate_px=100.0)
    canvas = draw_overlay(image, features, report).astype(float)
    on_circle = canvas[250, 400]  # 100 px right of the prediction, on the gate's circle
    expected = GATE_ALPHA * np.array(CYAN) + (1 - GATE_ALPHA) * 128
    assert np.allclose(on_circle, expected, atol=25)
    assert np.all(canvas[250, 350] == 128)  # inside the gate the image is untouched


def test_status_band_and_colour_key():
    image = np.full((H, W), 200, np.uint8)
    features, report = frame_and_report(10**9)
    canvas = draw_overlay(image, features, report)
    top, bottom = canvas[:22], canvas[-20:]
    # A dark band under the status text: mostly dark, one copy of the text in white (no offset shadow).
    assert np.median(top) < 60
    assert np.median(bottom) < 60
    for _, colour in LEGEND:  # every colour of the key appears in the bottom band
        assert np.any(np.all(np.abs(bottom.astype(int) - colour) < 40, axis=-1)), colour
    assert GREEN in [c for _, c in LEGEND] and MAGENTA in [c for _, c in LEGEND]
