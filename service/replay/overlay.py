"""A picture per camera frame: what the filter saw and what it made of it (thesis Fig. 3.4).

Drawn on the frame: every extracted feature (small yellow dots), each landmark's predicted
pixel with its search gate (cyan cross and circle), accepted matches (green line from the
prediction to the feature, with the landmark id), landmarks born in this frame (magenta
squares with their ids), and a status line. Files are ``<t_ns>.png`` in the output folder.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from vtolpose.drivers.files.frames_csv import write_png
from vtolpose.estimator.vision.camera_pipeline import FrameReport
from vtolpose.estimator.vision.features import FrameFeatures

YELLOW, CYAN, GREEN, MAGENTA, RED, WHITE = (0, 220, 255), (255, 220, 0), (0, 230, 0), (255, 0, 255), (0, 0, 255), (255, 255, 255)


def _pt(uv: np.ndarray) -> tuple[int, int]:
    return int(round(float(uv[0]))), int(round(float(uv[1])))


def draw_overlay(image: np.ndarray, features: FrameFeatures, report: FrameReport) -> np.ndarray:
    """The annotated BGR picture of one frame."""
    canvas = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    for uv in features.keypoints:
        cv2.circle(canvas, _pt(uv), 1, YELLOW, -1, cv2.LINE_AA)
    gate = int(round(report.gate_px))
    predicted = {int(i): uv for i, uv in zip(report.predicted_ids, report.predicted_uv)}
    for uv in predicted.values():
        p = _pt(uv)
        cv2.circle(canvas, p, gate, CYAN, 1, cv2.LINE_AA)
        cv2.drawMarker(canvas, p, CYAN, cv2.MARKER_CROSS, 9, 1, cv2.LINE_AA)
    for lm_id, f in zip(report.matched_ids, report.matched_features):
        uv = features.keypoints[f]
        if int(lm_id) in predicted:
            cv2.line(canvas, _pt(predicted[int(lm_id)]), _pt(uv), GREEN, 1, cv2.LINE_AA)
        cv2.circle(canvas, _pt(uv), 4, GREEN, 1, cv2.LINE_AA)
        cv2.putText(canvas, str(int(lm_id)), (_pt(uv)[0] + 5, _pt(uv)[1] - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.35, GREEN, 1, cv2.LINE_AA)
    for lm_id, f in zip(report.new_ids, report.new_features):
        x, y = _pt(features.keypoints[f])
        cv2.rectangle(canvas, (x - 3, y - 3), (x + 3, y + 3), MAGENTA, 1)
        cv2.putText(canvas, str(int(lm_id)), (x + 5, y + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, MAGENTA, 1, cv2.LINE_AA)
    if report.accepted:
        status = (f"t={report.t_ns * 1e-9:.3f}s  features {report.n_features}  in view {report.candidates}  "
                  f"matched {report.n_matches}  new {len(report.new_ids)}  map {report.n_landmarks}")
        colour = WHITE
    else:
        status, colour = f"t={report.t_ns * 1e-9:.3f}s  REJECTED: {report.reason}", RED
    cv2.putText(canvas, status, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(canvas, status, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
    return canvas


class OverlayWriter:
    """``on_frame`` callback for :func:`vtolpose.service.replay.session.replay`: one PNG per frame into ``folder``."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.written = 0

    def __call__(self, image: np.ndarray | None, features: FrameFeatures, report: FrameReport) -> None:
        if image is None:
            return  # nothing to draw on; the report counts the unreadable frame
        write_png(self.folder / f"{report.t_ns}.png", draw_overlay(image, features, report))
        self.written += 1
