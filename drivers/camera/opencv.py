"""Any camera OpenCV can open (V4L2 device, GStreamer pipeline, video file) as grey frames.

Frames are dated on the host clock when ``VideoCapture.read`` returned, less the configured
exposure/transfer latency, so they share the IMU's clock. Colour sources are converted to grey
(the estimator works on intensity only).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from vtolpose.config.sections import CameraSection
from vtolpose.drivers.camera.common import CameraUnavailable
from vtolpose.estimator.core.measurements import CameraFrame

__all__ = ["OpenCvCamera", "OpenCvCameraConfig"]

log = logging.getLogger(__name__)


@dataclass(slots=True)
class OpenCvCameraConfig:
    source: int | str = 0        # device index, device path, file or pipeline
    fps: float | None = None     # requested frame rate (devices only; None: the device's default)
    width: int | None = None
    height: int | None = None
    latency_s: float = 0.0

    @classmethod
    def from_section(cls, camera: CameraSection, device: str | None = None) -> "OpenCvCameraConfig":
        text = device if device is not None else camera.device
        source: int | str = 0 if text is None else int(text) if str(text).isdigit() else str(text)
        return cls(source, camera.fps, camera.width, camera.height, camera.latency_s)


class OpenCvCamera:
    def __init__(self, config: OpenCvCameraConfig, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.config = config
        self._clock = clock
        self._cap: cv2.VideoCapture | None = None
        self.seq = 0
        self.ended = False   # a file source has no more frames
        self.failures = 0

    def open(self) -> str:
        """Open the source; returns a one-line description, raises CameraUnavailable if it cannot."""
        cfg = self.config
        cap = cv2.VideoCapture(cfg.source)
        if not cap.isOpened():
            cap.release()
            raise CameraUnavailable(
                f"OpenCV could not open camera source {cfg.source!r} (no such device or file, or no backend "
                f"for it); set sensors.camera.device, or sensors.camera.type: none to run without a camera")
        for prop, value in ((cv2.CAP_PROP_FPS, cfg.fps), (cv2.CAP_PROP_FRAME_WIDTH, cfg.width),
                            (cv2.CAP_PROP_FRAME_HEIGHT, cfg.height)):
            if value and isinstance(cfg.source, int):
                cap.set(prop, float(value))
        self._cap, self.ended = cap, False
        return self.describe()

    def describe(self) -> str:
        cap = self._cap
        if cap is None:
            return f"OpenCV source {self.config.source!r} (closed)"
        w, h, fps = (cap.get(p) for p in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT, cv2.CAP_PROP_FPS))
        return f"OpenCV {cap.getBackendName()} source {self.config.source!r}: {int(w)} x {int(h)} at {fps:g} fps"

    def read(self, timeout_s: float = 0.0) -> CameraFrame | None:
        """The next frame, or None at the end of a file or on a failed grab (counted).

        OpenCV's read blocks until a frame arrives; ``timeout_s`` is accepted for a common
        camera interface and unused.
        """
        if self._cap is None or self.ended:
            return None
        ok, image = self._cap.read()
        t_ns = self._clock() - int(round(self.config.latency_s * 1e9))
        if not ok or image is None:
            self.failures += 1
            if isinstance(self.config.source, str) and self._cap.get(cv2.CAP_PROP_FRAME_COUNT) > 0:
                self.ended = True
            return None
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        self.seq += 1
        return CameraFrame(t_ns, np.ascontiguousarray(image, dtype=np.uint8), self.seq)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
        self._cap = None

    def __enter__(self) -> "OpenCvCamera":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
