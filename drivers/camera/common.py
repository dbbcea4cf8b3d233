"""What the camera drivers share: the camera protocol and the "no camera" error.

Every driver has ``open() -> description``, ``read(timeout_s) -> CameraFrame | None`` and
``close()``; the service decides from ``sensors.camera.required`` whether a CameraUnavailable
stops it or only means running without images.
"""

from __future__ import annotations

from typing import Protocol

from vtolpose.estimator.core.measurements import CameraFrame

__all__ = ["Camera", "CameraUnavailable"]


class CameraUnavailable(RuntimeError):
    """No usable camera: the message says what is missing and how to run without it."""


class Camera(Protocol):
    def open(self) -> str: ...
    def read(self, timeout_s: float = ...) -> CameraFrame | None: ...
    def close(self) -> None: ...
