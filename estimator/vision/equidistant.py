"""Kannala–Brandt equidistant (fisheye) lens: OpenCV ``cv2.fisheye``'s k1..k4 model.

Why a second model: wide-angle and fisheye lenses bend rays far more than a radial polynomial in
r² can describe; the equidistant model maps the ray's angle from the optical axis instead::

    r = |(x, y)|,  θ = atan(r),  θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)
    (x_d, y_d) = (θ_d / r) (x, y)

on normalised pinhole coordinates ``(x, y) = (X/Z, Y/Z)``, so the camera model keeps one
interface for both lenses: distort, its Jacobian, and the inverse.
"""

from __future__ import annotations

import numpy as np

SMALL_R = 1e-8  # below this radius the ratio θ_d/r is taken from its series (1 at r = 0)


def _theta_d(theta: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """θ_d(θ) and its derivative dθ_d/dθ."""
    t2 = theta * theta
    poly = 1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))
    dpoly = 1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + t2 * 9.0 * k[3])))
    return theta * poly, dpoly


def distort(xn: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Distorted normalised coordinates of undistorted ones, ``(N, 2)``."""
    r = np.hypot(xn[..., 0], xn[..., 1])
    theta_d, _ = _theta_d(np.arctan(r), k)
    small = r < SMALL_R
    scale = np.where(small, 1.0, theta_d / np.where(small, 1.0, r))
    return xn * scale[..., None]


def jacobian(xn: np.ndarray, k: np.ndarray) -> np.ndarray:
    """``∂(x_d, y_d)/∂(x, y)``, shape ``(N, 2, 2)``: ``s I + (ds/dr / r) x xᵀ`` with ``s = θ_d / r``."""
    r = np.hypot(xn[..., 0], xn[..., 1])
    small = r < SMALL_R
    r_safe = np.where(small, 1.0, r)
    theta = np.arctan(r)
    theta_d, dtheta_d = _theta_d(theta, k)
    s = np.where(small, 1.0, theta_d / r_safe)
    ds_dr = (dtheta_d / (1.0 + r * r) * r - theta_d) / (r_safe * r_safe)
    # As r → 0: s ≈ 1 + (k1 − 1/3) r², so (ds/dr) / r → 2 (k1 − 1/3).
    ds_over_r = np.where(small, 2.0 * (k[0] - 1.0 / 3.0), ds_dr / r_safe)
    J = ds_over_r[..., None, None] * (xn[..., :, None] * xn[..., None, :])
    J[..., 0, 0] += s
    J[..., 1, 1] += s
    return J


def undistort(xd: np.ndarray, k: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Undistorted normalised coordinates: θ from θ_d by Newton's method, then ``r = tan θ``.

    Solving for the angle (one unknown, well conditioned up to the edge of a fisheye's view)
    instead of for (x, y) keeps it accurate where ``r = tan θ`` grows fast.
    """
    theta_d = np.hypot(xd[..., 0], xd[..., 1])
    theta = theta_d.copy()
    for _ in range(iterations):
        value, slope = _theta_d(theta, k)
        step = (value - theta_d) / slope
        theta = theta - step
        if float(np.max(np.abs(step), initial=0.0)) < 1e-15:
            break
    small = theta_d < SMALL_R
    scale = np.where(small, 1.0, np.tan(theta) / np.where(small, 1.0, theta_d))
    return xd * scale[..., None]
