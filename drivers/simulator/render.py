"""Camera frames of a simulated flight: the textured height field seen from the exact pose.

Each pixel's ray is cast against the scenario's ground ``down = ground_height(n, e)`` by a
fixed number of fixed-point steps (intersect the plane at the height found under the previous
guess), on a grid every ``grid_step`` pixels; the ground coordinates are then interpolated to
full resolution and the texture is looked up with ``cv2.remap``. Lens distortion is exact:
the rays come from undistorting every grid pixel through the same camera model the estimator
uses. Then the camera: vignetting, a slowly wandering exposure, shot and read noise, and a
short linear motion blur along the image motion during the exposure.

Determinism: all randomness comes from the simulator's camera stream (``STREAM_CAMERA``), drawn
frame by frame in order, so the same flight and seed always give the same images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from vtolpose.drivers.simulator.flight import STREAM_CAMERA, SimulatedFlight, _rng, sample_times_ns
from vtolpose.drivers.simulator.textures import Appearance, appearance_for
from vtolpose.estimator.core.calibration import CameraCalibration
from vtolpose.estimator.vision.camera_model import CameraModel

R_BC_DOWN = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # x right, y back, z down


def default_camera() -> CameraCalibration:
    """A Marlin-like grey camera (656 × 494 at 7.5 Hz, ~60° wide), looking down, beside the IMU."""
    return CameraCalibration(
        width=656, height=494, fx=570.0, fy=570.0, cx=327.5, cy=246.5,
        distortion=np.array([-0.12, 0.05, 5e-4, -3e-4, 0.0]),
        R_BC=R_BC_DOWN, t_BC=np.array([0.05, 0.0, 0.05]), rate_hz=7.5, time_offset_s=0.0,
    )


@dataclass(frozen=True, slots=True)
class RenderOptions:
    grid_step: int = 4  # rays are cast every this many pixels, then interpolated
    ray_iterations: int = 5
    exposure_s: float = 0.004  # motion blur integrates over this
    exposure_sigma: float = 0.12  # log-gain std of the slowly wandering auto-exposure
    exposure_correlation: float = 0.97  # per frame
    read_noise_dn: float = 1.5
    shot_noise_dn: float = 0.04  # variance per DN of signal
    vignetting: float = 0.25  # brightness lost at the image corners


class FrameRenderer:
    """Renders the flight's ground as seen by ``camera`` at any time."""

    def __init__(self, flight: SimulatedFlight, camera: CameraCalibration, options: RenderOptions | None = None) -> None:
        self.flight = flight
        self.camera = camera
        self.options = opts = options or RenderOptions()
        self.model = CameraModel(camera)
        self.appearance: Appearance = appearance_for(flight.scenario)
        self.ground = flight.scenario.ground_height
        w, h, step = camera.width, camera.height, opts.grid_step
        # Grid nodes on pixel centres 0, step, ... up to and including the last pixel.
        self._gu = np.unique(np.r_[np.arange(0, w, step), w - 1]).astype(float)
        self._gv = np.unique(np.r_[np.arange(0, h, step), h - 1]).astype(float)
        gu, gv = np.meshgrid(self._gu, self._gv)
        self._rays_c = self.model.rays(np.stack([gu.ravel(), gv.ravel()], axis=1))
        # Full-resolution sampling positions of the grid (for cv2.remap-based upsampling).
        cols = np.interp(np.arange(w), self._gu, np.arange(len(self._gu))).astype(np.float32)
        rows = np.interp(np.arange(h), self._gv, np.arange(len(self._gv))).astype(np.float32)
        self._up_x, self._up_y = np.meshgrid(cols, rows)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = ((xx - camera.cx) / camera.fx) ** 2 + ((yy - camera.cy) / camera.fy) ** 2
        self._vignette = (1.0 - opts.vignetting * np.clip(r2 / 0.36, 0.0, 1.0)).astype(np.float32)

    def pose(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera centres (N, 3) and camera→world rotations (N, 3, 3) at times ``t_s``."""
        k = self.flight.trajectory.kinematics(np.atleast_1d(np.asarray(t_s, dtype=float)))
        R_WB = k.rotation()
        return k.p + R_WB @ self.camera.t_BC, R_WB @ self.camera.R_BC

    def _cast(self, c_w: np.ndarray, R_WC: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Ground points hit by the grid rays: (n, e, down) grids and the metres per pixel at the centre."""
        rays = self._rays_c @ R_WC.T
        rd = np.maximum(rays[:, 2], 1e-3)  # rays at or above the horizon hit the ground very far away
        t = np.full(len(rays), (float(self.ground(c_w[0], c_w[1])) - c_w[2]))
        for _ in range(self.options.ray_iterations):
            g = self.ground(c_w[0] + t * rays[:, 0], c_w[1] + t * rays[:, 1])
            t = np.maximum((g - c_w[2]) / rd, 1e-3)
        pts = c_w + t[:, None] * rays
        shape = (len(self._gv), len(self._gu))
        # The rays are [x, y, 1] in the camera, so t is the depth along the optical axis.
        return (*(pts[:, i].reshape(shape).astype(np.float32) for i in range(3)), float(np.median(t)) / self.camera.fx)

    def radiance(self, c_w: np.ndarray, R_WC: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free brightness in [0, 1] seen from camera pose (c_w, R_WC), and the ground point at the centre."""
        import cv2  # on first use: a process that never needs OpenCV never loads it (~16 MB)

        n, e, d, footprint = self._cast(c_w, R_WC)
        full = [cv2.remap(g, self._up_x, self._up_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) for g in (n, e, d)]
        mid = (len(self._gv) // 2, len(self._gu) // 2)
        return self.appearance.radiance(*full, footprint), np.array([n[mid], e[mid], d[mid]], dtype=float)

    def _blur_kernel(self, c_w: np.ndarray, R_WC: np.ndarray, point: np.ndarray) -> np.ndarray | None:
        """Line kernel along the image motion of the ground ``point`` between the two poses of the exposure."""
        uv0 = self.model.project((R_WC[0].T @ (point - c_w[0]))[None])[0][0]
        uv1 = self.model.project((R_WC[1].T @ (point - c_w[1]))[None])[0][0]
        motion = uv1 - uv0
        length = float(np.hypot(*motion))
        if not math.isfinite(length) or length < 0.7:
            return None
        size = int(math.ceil(length)) | 1
        kernel = np.zeros((size, size), np.float32)
        centre = size // 2
        steps = max(2 * size, 8)
        for a in np.linspace(-0.5, 0.5, steps):
            x, y = centre + a * motion[0], centre + a * motion[1]
            kernel[int(round(y)), int(round(x))] += 1.0
        return kernel / kernel.sum()

    def frames(self, seed: int) -> Iterator[tuple[int, np.ndarray]]:
        """``(t_ns, uint8 image)`` for every frame time of the flight, in order."""
        import cv2

        opts = self.options
        rng = _rng(seed, STREAM_CAMERA)
        flight = self.flight
        epoch = int(flight.truth.t_ns[0]) if len(flight.truth.t_ns) else 0
        times = sample_times_ns(self.camera.rate_hz, flight.duration_s, epoch)
        t_s = (times - epoch) * 1e-9
        half = 0.5 * opts.exposure_s
        c_w, R_WC = self.pose(t_s)
        c_open, R_open = self.pose(np.maximum(t_s - half, 0.0))
        c_shut, R_shut = self.pose(np.minimum(t_s + half, flight.duration_s))
        log_gain = rng.standard_normal() * opts.exposure_sigma
        rho = opts.exposure_correlation
        for k, t_ns in enumerate(times.tolist()):
            log_gain = rho * log_gain + math.sqrt(1.0 - rho * rho) * opts.exposure_sigma * rng.standard_normal()
            radiance, centre = self.radiance(c_w[k], R_WC[k])
            signal = radiance * self._vignette * np.float32(255.0 * math.exp(log_gain))
            kernel = None
            if opts.exposure_s > 0.0:
                kernel = self._blur_kernel(np.array([c_open[k], c_shut[k]]), np.array([R_open[k], R_shut[k]]), centre)
            if kernel is not None:
                signal = cv2.filter2D(signal, -1, kernel, borderType=cv2.BORDER_REPLICATE)
            sigma = np.sqrt(opts.read_noise_dn**2 + opts.shot_noise_dn * np.maximum(signal, 0.0))
            signal += sigma * rng.standard_normal(signal.shape, dtype=np.float32)
            yield t_ns, np.clip(np.rint(signal), 0, 255).astype(np.uint8)


def render_frames(
    flight: SimulatedFlight, camera: CameraCalibration | None = None, options: RenderOptions | None = None
) -> Iterator[tuple[int, np.ndarray]]:
    """The frames of ``flight`` with ``camera`` (default: :func:`default_camera`), seeded by the flight."""
    return FrameRenderer(flight, camera or default_camera(), options).frames(flight.seed)
