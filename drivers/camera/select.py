"""The camera driver that ``sensors.camera.type`` names, not yet opened.

Kept apart from ``common`` so that each driver imports only what it shares, and this module is
the one place that knows every driver (no import cycle between them).
"""

from __future__ import annotations

from vtolpose.config.sections import CameraSection
from vtolpose.drivers.camera.common import Camera, CameraUnavailable


def camera_from_config(camera: CameraSection, kind: str | None = None, device: str | None = None) -> Camera:
    """The driver named by ``sensors.camera.type`` (or ``kind``), not yet opened."""
    kind = kind or camera.type
    if kind == "opencv":
        from vtolpose.drivers.camera.opencv import OpenCvCamera, OpenCvCameraConfig

        return OpenCvCamera(OpenCvCameraConfig.from_section(camera, device))
    if kind == "dc1394":
        from vtolpose.drivers.camera.dc1394 import Dc1394Camera, Dc1394Config

        return Dc1394Camera(Dc1394Config.from_section(camera, device))
    raise CameraUnavailable(f"sensors.camera.type is {kind!r}: no camera configured")
