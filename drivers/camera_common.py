"""What the camera drivers share: the "no camera" error and the choice of driver from config.

Every driver has ``open() -> description``, ``read(timeout_s) -> CameraFrame | None`` and
``close()``; the service decides from ``sensors.camera.required`` whether a CameraUnavailable
stops it or only means running without images.
"""

from __future__ import annotations

from typing import Any, Mapping, Protocol

from estimator.measurements import CameraFrame

__all__ = ["Camera", "CameraUnavailable", "camera_from_config"]


class CameraUnavailable(RuntimeError):
    """No usable camera: the message says what is missing and how to run without it."""


class Camera(Protocol):
    def open(self) -> str: ...
    def read(self, timeout_s: float = ...) -> CameraFrame | None: ...
    def close(self) -> None: ...


def camera_from_config(cfg: Mapping[str, Any], kind: str | None = None, device: str | None = None) -> Camera:
    """The driver named by ``sensors.camera.type`` (or ``kind``), not yet opened."""
    kind = kind or cfg["sensors.camera.type"]
    if kind == "opencv":
        from drivers.camera_opencv import OpenCvCamera, OpenCvCameraConfig

        return OpenCvCamera(OpenCvCameraConfig.from_config(cfg, device))
    if kind == "dc1394":
        from drivers.camera_dc1394 import Dc1394Camera, Dc1394Config

        return Dc1394Camera(Dc1394Config.from_config(cfg, device))
    raise CameraUnavailable(f"sensors.camera.type is {kind!r}: no camera configured")
