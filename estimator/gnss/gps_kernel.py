"""A GPS fix's whole EKF update in one compiled call: lever arm, residual, Jacobian, noise and the update.

In Python the fix costs a dozen calls on three-element arrays (rotation, lever arm, prediction,
Jacobian, noise, each wrapper dearer than its arithmetic) around the compiled update. Here the same
operations run in one call, in the same order and on the same formulas as
:class:`~vtolpose.estimator.gnss.gps_update.GpsModel` and
:func:`~vtolpose.estimator.core.update_kernel.small_update`, so the filter's numbers do not change (a
test holds the two paths bit for bit). Cached and loaded as the other kernels are
(``service.runtime.daemon.load_compiled_kernels``).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vtolpose.estimator.core.update_kernel import NO_HELD, small_update


@numba.njit(cache=True, nogil=True)
def lever_arm_world(q: np.ndarray, lever_b: np.ndarray) -> np.ndarray:
    """``R(q) l``: the rotation as :func:`~vtolpose.estimator.core.rotation.rot_of` builds it, then the product."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    r = np.empty((3, 3))
    r[0, 0], r[0, 1], r[0, 2] = 1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)
    r[1, 0], r[1, 1], r[1, 2] = 2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)
    r[2, 0], r[2, 1], r[2, 2] = 2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)
    return np.dot(r, lever_b)


@numba.njit(cache=True, nogil=True)
def gps_update(cov: np.ndarray, p: np.ndarray, q: np.ndarray, lever_b: np.ndarray, fix: np.ndarray, var_h: float,
               var_v: float, gate: float, held: np.ndarray) -> tuple[int, float, np.ndarray]:
    """Fuse a fix ``fix`` (NED, m) with variances ``var_h``, ``var_h``, ``var_v`` into ``cov`` (in place), the
    antenna ``lever_b`` from the IMU: ``small_update``'s (outcome code, NIS, correction δx)."""
    arm = lever_arm_world(q, lever_b)
    residual = fix - (p + arm)
    H = np.zeros((3, 9))
    H[0, 0], H[1, 1], H[2, 2] = 1.0, 1.0, 1.0
    ax, ay, az = arm[0], arm[1], arm[2]
    # -skew(arm), its zero diagonal negated too (as numpy's -skew gives it).
    H[0, 6], H[0, 7], H[0, 8] = -0.0, az, -ay
    H[1, 6], H[1, 7], H[1, 8] = -az, -0.0, ax
    H[2, 6], H[2, 7], H[2, 8] = ay, -ax, -0.0
    R = np.zeros((3, 3))
    R[0, 0], R[1, 1], R[2, 2] = var_h, var_h, var_v
    return small_update(cov, 0, 9, H, residual, R, gate, held)


def warm_up() -> None:
    """Compile (or load from the cache) for the argument types the filter passes (a mask of held states, or
    none, is the same type)."""
    gps_update(np.eye(15), np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3), np.zeros(3), 1.0, 2.0, math.inf,
               NO_HELD)
