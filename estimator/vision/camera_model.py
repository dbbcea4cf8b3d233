"""Pinhole camera with radial-tangential distortion (OpenCV's k1, k2, p1, p2, k3) or an
equidistant fisheye lens (``cv2.fisheye``'s k1..k4, :mod:`.equidistant`).

Why our own instead of ``cv2.projectPoints``: the EKF needs the projection *and* its Jacobian
for a whole batch of landmarks every frame, without OpenCV's Rodrigues/translation arguments
and per-call overhead. OpenCV stays the test oracle.

Normalised coordinates ``x = X/Z, y = Y/Z`` (camera frame: x right, y down, z forward) are
distorted by::

    r² = x² + y²,  k = 1 + k1 r² + k2 r⁴ + k3 r⁶
    x_d = k x + 2 p1 x y + p2 (r² + 2 x²)
    y_d = k y + p1 (r² + 2 y²) + 2 p2 x y
    u = fx x_d + cx,  v = fy y_d + cy

(the equidistant lens replaces the first three lines by its own map of ``(x, y)``).

All functions take stacks: points ``(N, 3)``, normalised or pixel coordinates ``(N, 2)``.
"""

from __future__ import annotations

import numpy as np

from vtolpose.estimator.core.calibration import CameraCalibration
from vtolpose.estimator.vision import equidistant

MIN_DEPTH = 1e-6  # a point must be this far in front of the camera to be projected


def _inverse_2x2(m: np.ndarray) -> np.ndarray:
    """Inverses of a stack of 2 × 2 matrices in closed form (cheaper than a batched LAPACK call)."""
    a, b, c, d = m[..., 0, 0], m[..., 0, 1], m[..., 1, 0], m[..., 1, 1]
    inv = np.empty_like(m)
    det = a * d - b * c
    inv[..., 0, 0], inv[..., 0, 1], inv[..., 1, 0], inv[..., 1, 1] = d / det, -b / det, -c / det, a / det
    return inv


class CameraModel:
    """Projection, undistortion and their Jacobians for one calibrated camera."""

    def __init__(self, calibration: CameraCalibration) -> None:
        self.calibration = calibration
        self.width, self.height = int(calibration.width), int(calibration.height)
        self.fx, self.fy = float(calibration.fx), float(calibration.fy)
        self.cx, self.cy = float(calibration.cx), float(calibration.cy)
        self.fisheye = calibration.model == "equidistant"
        self.coefficients = np.array(calibration.distortion, dtype=float)
        if self.fisheye:
            self.k1 = self.k2 = self.p1 = self.p2 = self.k3 = 0.0
        else:
            self.k1, self.k2, self.p1, self.p2, self.k3 = (float(c) for c in calibration.distortion)

    # ------------------------------------------------------------------ distortion
    def distort(self, xn: np.ndarray) -> np.ndarray:
        """Distorted normalised coordinates of undistorted ones, ``(N, 2)``."""
        if self.fisheye:
            return equidistant.distort(xn, self.coefficients)
        x, y = xn[..., 0], xn[..., 1]
        r2 = x * x + y * y
        k = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        xy = x * y
        xd = k * x + 2.0 * self.p1 * xy + self.p2 * (r2 + 2.0 * x * x)
        yd = k * y + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * xy
        return np.stack([xd, yd], axis=-1)

    def distort_jacobian(self, xn: np.ndarray) -> np.ndarray:
        """``∂(x_d, y_d) / ∂(x, y)``, shape ``(N, 2, 2)``."""
        if self.fisheye:
            return equidistant.jacobian(xn, self.coefficients)
        x, y = xn[..., 0], xn[..., 1]
        r2 = x * x + y * y
        k = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        dk_dr2 = self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2)
        J = np.empty(xn.shape[:-1] + (2, 2))
        J[..., 0, 0] = k + 2.0 * x * x * dk_dr2 + 2.0 * self.p1 * y + 6.0 * self.p2 * x
        J[..., 0, 1] = 2.0 * x * y * dk_dr2 + 2.0 * self.p1 * x + 2.0 * self.p2 * y
        J[..., 1, 0] = 2.0 * x * y * dk_dr2 + 2.0 * self.p1 * x + 2.0 * self.p2 * y
        J[..., 1, 1] = k + 2.0 * y * y * dk_dr2 + 6.0 * self.p1 * y + 2.0 * self.p2 * x
        return J

    # ------------------------------------------------------------------ projection
    def normalized_to_pixel(self, xn: np.ndarray) -> np.ndarray:
        d = self.distort(xn)
        return np.stack([self.fx * d[..., 0] + self.cx, self.fy * d[..., 1] + self.cy], axis=-1)

    def project(self, points_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels of camera-frame points and a mask of those in front of the camera.

        Points behind (or on) the image plane get NaN pixels, so they can never pass a gate.
        """
        points_c = np.asarray(points_c, dtype=float)
        z = points_c[..., 2]
        front = z > MIN_DEPTH
        safe_z = np.where(front, z, 1.0)
        xn = points_c[..., :2] / safe_z[..., None]
        uv = self.normalized_to_pixel(xn)
        uv[~front] = np.nan
        return uv, front

    def project_jacobian(self, points_c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixels, in-front mask and ``∂(u, v)/∂(X, Y, Z)`` of shape ``(N, 2, 3)``."""
        points_c = np.asarray(points_c, dtype=float)
        z = points_c[..., 2]
        front = z > MIN_DEPTH
        inv_z = 1.0 / np.where(front, z, 1.0)
        xn = points_c[..., :2] * inv_z[..., None]
        uv = self.normalized_to_pixel(xn)
        uv[~front] = np.nan
        # ∂xn/∂P = [[1/z, 0, -x/z], [0, 1/z, -y/z]]; then distortion, then focal lengths.
        dxn = np.zeros(points_c.shape[:-1] + (2, 3))
        dxn[..., 0, 0] = inv_z
        dxn[..., 1, 1] = inv_z
        dxn[..., 0, 2] = -xn[..., 0] * inv_z
        dxn[..., 1, 2] = -xn[..., 1] * inv_z
        D = self.distort_jacobian(xn)
        D[..., 0, :] *= self.fx
        D[..., 1, :] *= self.fy
        return uv, front, D @ dxn

    # ---------------------------------------------------------------- undistortion
    def undistort(self, uv: np.ndarray, iterations: int = 8) -> np.ndarray:
        """Normalised undistorted coordinates of pixels, by Newton's method on the model.

        Newton (with the analytic Jacobian) converges in a few steps anywhere the model is
        invertible, unlike the fixed-point iteration, which slows down near the image corners.
        """
        uv = np.asarray(uv, dtype=float)
        xd = np.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], axis=-1)
        if self.fisheye:
            return equidistant.undistort(xd, self.coefficients)
        if self.k1 == self.k2 == self.k3 == self.p1 == self.p2 == 0.0:
            return xd
        x = xd.copy()
        for _ in range(iterations):
            residual = self.distort(x) - xd
            x = x - (_inverse_2x2(self.distort_jacobian(x)) @ residual[..., None])[..., 0]
            if float(np.max(np.abs(residual), initial=0.0)) < 1e-13:
                break
        return x

    def undistort_jacobian(self, xn: np.ndarray) -> np.ndarray:
        """``∂(x, y)/∂(u, v)`` at undistorted points ``xn``: the inverse of the forward Jacobian."""
        D = self.distort_jacobian(xn)
        D[..., 0, :] *= self.fx
        D[..., 1, :] *= self.fy
        return _inverse_2x2(D)

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Camera-frame viewing directions ``[x, y, 1]`` (not normalised) of pixels."""
        xn = self.undistort(uv)
        return np.concatenate([xn, np.ones(xn.shape[:-1] + (1,))], axis=-1)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Pixels inside the image (by ``margin`` px); NaN pixels are outside."""
        u, v = uv[..., 0], uv[..., 1]
        with np.errstate(invalid="ignore"):
            return (u >= -0.5 + margin) & (u <= self.width - 0.5 - margin) & (v >= -0.5 + margin) & (v <= self.height - 0.5 - margin)
