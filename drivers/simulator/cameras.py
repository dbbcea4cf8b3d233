"""Cameras for the camera test matrix: a lens model at a resolution and frame rate.

Lenses: ``pinhole`` (no distortion), ``radtan`` (a mild barrel lens, OpenCV k1 k2 p1 p2 k3) and
``equidistant`` (a fisheye, ``cv2.fisheye`` k1..k4, about 120° across). The pinhole and
radial-tangential ones see about 70° across at any width, so only the pixel count changes with
the resolution; 656 × 494 is :func:`render.default_camera`'s own lens. All look down, mounted
beside the IMU as the default camera is.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from vtolpose.drivers.simulator.render import R_BC_DOWN, default_camera
from vtolpose.estimator.core.calibration import CameraCalibration

LENSES = ("pinhole", "radtan", "equidistant")
RADTAN = np.array([-0.10, 0.03, 3e-4, -2e-4, 0.0])
EQUIDISTANT = np.array([0.02, -0.01, 0.003, -0.0005])
FOCAL_PER_WIDTH = {"pinhole": 0.72, "radtan": 0.72, "equidistant": 0.47}  # fx / width


def matrix_camera(lens: str, width: int, height: int, rate_hz: float) -> CameraCalibration:
    """A downward camera with ``lens`` at ``width`` × ``height`` and ``rate_hz``."""
    if lens not in LENSES:
        raise ValueError(f"unknown lens {lens!r}; choose one of {list(LENSES)}")
    if (width, height) == (656, 494) and lens == "radtan":
        return dataclasses.replace(default_camera(), rate_hz=rate_hz)
    f = FOCAL_PER_WIDTH[lens] * width
    distortion = {"pinhole": None, "radtan": RADTAN, "equidistant": EQUIDISTANT}[lens]
    return CameraCalibration(
        width=width, height=height, fx=f, fy=f, cx=(width - 1) / 2.0, cy=(height - 1) / 2.0, distortion=distortion,
        R_BC=R_BC_DOWN, t_BC=np.array([0.05, 0.0, 0.05]), rate_hz=rate_hz,
        model="equidistant" if lens == "equidistant" else "radtan",
    )
