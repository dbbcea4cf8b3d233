"""The IMU step written plainly in numpy: the oracle the compiled step (``propagation_kernel.step``) is tested
against, and that is itself tested against central differences (tests/test_propagator.py).

The runtime has one implementation, the compiled one; this one stays here because a slow, obvious
reading of the equations (``propagator``'s module docstring) is what a test can trust.
"""

from __future__ import annotations

import math

import numpy as np

from vtolpose.estimator.core.rotation import quat_product, right_jacobian, rot_of, rotvec_quat, skew
from vtolpose.estimator.core.state import StateLayout


def quat_times_rotvec(q: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """``q ⊗ Exp(φ)``, normalised: the body-frame attitude increment."""
    out = np.array(quat_product(*q.tolist(), *rotvec_quat(*phi.tolist())))
    return out / math.sqrt(float(out @ out))


def corrected(b_g: np.ndarray, b_a: np.ndarray, dtheta: np.ndarray, dvel: np.ndarray, dt: float):
    """Bias-corrected rotation vector and mean specific force (start-of-step body frame)."""
    phi = dtheta - b_g * dt
    dv = dvel - (0.5 * dt) * np.cross(b_g, dvel)
    return phi, dv / dt - b_a


def integrate_nominal(p: np.ndarray, v: np.ndarray, q: np.ndarray, b_g: np.ndarray, b_a: np.ndarray,
                      dtheta: np.ndarray, dvel: np.ndarray, dt: float,
                      gravity: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One nominal step over an IMU delta. Returns ``(p', v', q', a_W)``."""
    phi, f = corrected(b_g, b_a, dtheta, dvel, dt)
    a_w = np.array(rot_of(*q.tolist())) @ f + gravity
    return p + v * dt + (0.5 * dt * dt) * a_w, v + a_w * dt, quat_times_rotvec(q, phi), a_w


def error_transition(q: np.ndarray, b_g: np.ndarray, b_a: np.ndarray, dtheta: np.ndarray, dvel: np.ndarray,
                     dt: float, layout: StateLayout) -> np.ndarray:
    """Jacobian F of the robot error state (global attitude error) over one step."""
    n = layout.robot_dim
    phi, f = corrected(b_g, b_a, dtheta, dvel, dt)
    r = np.array(rot_of(*q.tolist()))
    a_skew = skew(r @ f)
    F = np.eye(n)
    h2 = 0.5 * dt * dt
    F[0:3, 3:6] = dt * np.eye(3)
    F[0:3, 6:9] = -h2 * a_skew
    F[3:6, 6:9] = -dt * a_skew
    if layout.estimates_biases:
        r_new = np.array(rot_of(*quat_times_rotvec(q, phi).tolist()))
        d_a_d_bg = 0.5 * (r @ skew(dvel))
        F[0:3, 9:12] = h2 * d_a_d_bg
        F[3:6, 9:12] = dt * d_a_d_bg
        F[6:9, 9:12] = -dt * (r_new @ right_jacobian(phi))
        F[0:3, 12:15] = -h2 * r
        F[3:6, 12:15] = -dt * r
    return F
