"""A picture per camera frame: what the filter saw and what it made of it (thesis Fig. 3.4).

Drawn on the frame: every extracted feature (small yellow dots), each landmark's predicted
pixel with its search gate (cyan cross and circle), accepted matches (green line from the
prediction to the feature, with the landmark id), landmarks born in this frame (magenta
squares with their ids), a status line on a dark band at the top and a colour key at the
bottom. Gates are blended in at a third of their strength so that the image stays readable
under them. Files are ``<t_ns>.jpg`` with the time zero-padded to 20 digits, so that a plain
``ls`` lists them in time order; JPEG at quality 90 keeps a frame near 100 KB where a PNG of the
textured image took ~470 KB.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from vtolpose.estimator import FrameFeatures, FrameReport

YELLOW, CYAN, GREEN, MAGENTA, RED, WHITE = (0, 220, 255), (255, 220, 0), (0, 230, 0), (255, 0, 255), (0, 0, 255), (255, 255, 255)


def _pt(uv: np.ndarray) -> tuple[int, int]:
    return int(round(float(uv[0]))), int(round(float(uv[1])))


GATE_ALPHA = 0.35
JPEG_QUALITY = 90
LEGEND = (("feature", YELLOW), ("predicted + gate", CYAN), ("matched (id)", GREEN), ("new landmark", MAGENTA))
FONT = cv2.FONT_HERSHEY_SIMPLEX


def _band(canvas: np.ndarray, top: int, height: int) -> None:
    """Darken a full-width band so that text on it reads on any texture."""
    band = canvas[top:top + height]
    band[:] = (band * 0.25).astype(canvas.dtype)


def working_picture(image: np.ndarray, features: FrameFeatures) -> np.ndarray:
    """``image`` reduced to the features' frame size when the camera pipeline reduced it (the keypoints are there)."""
    height, width = features.image_shape[:2]
    if image.shape[:2] == (height, width) or not width or not height:
        return image
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def draw_overlay(image: np.ndarray, features: FrameFeatures, report: FrameReport) -> np.ndarray:
    """The annotated BGR picture of one frame, at the size the features were found on (the working width)."""
    image = working_picture(image, features)
    canvas = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    gate = int(round(report.gate_px))
    predicted = {int(i): uv for i, uv in zip(report.predicted_ids, report.predicted_uv)}
    if predicted:
        gates = canvas.copy()
        for uv in predicted.values():
            cv2.circle(gates, _pt(uv), gate, CYAN, 1, cv2.LINE_AA)
        cv2.addWeighted(gates, GATE_ALPHA, canvas, 1.0 - GATE_ALPHA, 0.0, dst=canvas)
    for uv in features.keypoints:
        cv2.circle(canvas, _pt(uv), 1, YELLOW, -1, cv2.LINE_AA)
    for uv in predicted.values():
        cv2.drawMarker(canvas, _pt(uv), CYAN, cv2.MARKER_CROSS, 9, 1, cv2.LINE_AA)
    for lm_id, f in zip(report.matched_ids, report.matched_features):
        uv = features.keypoints[f]
        if int(lm_id) in predicted:
            cv2.line(canvas, _pt(predicted[int(lm_id)]), _pt(uv), GREEN, 1, cv2.LINE_AA)
        cv2.circle(canvas, _pt(uv), 4, GREEN, 1, cv2.LINE_AA)
        cv2.putText(canvas, str(int(lm_id)), (_pt(uv)[0] + 5, _pt(uv)[1] - 5), FONT, 0.35, GREEN, 1, cv2.LINE_AA)
    for lm_id, f in zip(report.new_ids, report.new_features):
        x, y = _pt(features.keypoints[f])
        cv2.rectangle(canvas, (x - 3, y - 3), (x + 3, y + 3), MAGENTA, 1)
        cv2.putText(canvas, str(int(lm_id)), (x + 5, y + 12), FONT, 0.35, MAGENTA, 1, cv2.LINE_AA)
    if report.accepted:
        status = (f"t={report.t_ns * 1e-9:.3f}s  features {report.n_features}  in view {report.candidates}  "
                  f"matched {report.n_matches}  new {len(report.new_ids)}  map {report.n_landmarks}")
        colour = WHITE
    else:
        status, colour = f"t={report.t_ns * 1e-9:.3f}s  REJECTED: {report.reason}", RED
    _band(canvas, 0, 22)
    cv2.putText(canvas, status, (6, 16), FONT, 0.45, colour, 1, cv2.LINE_AA)
    height = canvas.shape[0]
    _band(canvas, height - 20, 20)
    x = 6
    for label, key_colour in LEGEND:
        cv2.circle(canvas, (x + 4, height - 10), 4, key_colour, -1, cv2.LINE_AA)
        cv2.putText(canvas, label, (x + 12, height - 6), FONT, 0.4, WHITE, 1, cv2.LINE_AA)
        x += 20 + cv2.getTextSize(label, FONT, 0.4, 1)[0][0]
    return canvas


def overlay_name(t_ns: int) -> str:
    """``<t_ns>.jpg`` zero-padded to 20 digits: name order is time order."""
    return f"{int(t_ns):020d}.jpg"


class OverlayWriter:
    """``on_frame`` callback for :func:`vtolpose.service.replay.session.replay`: one PNG per frame into ``folder``."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.written = 0

    def __call__(self, image: np.ndarray | None, features: FrameFeatures, report: FrameReport) -> None:
        if image is None:
            return  # nothing to draw on; the report counts the unreadable frame
        path = self.folder / overlay_name(report.t_ns)
        ok, data = cv2.imencode(".jpg", draw_overlay(image, features, report), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise OSError(f"{path}: could not encode the overlay as JPEG")
        path.write_bytes(data.tobytes())
        self.written += 1
