"""The EKF update of a small measurement (one to three rows: a GPS fix, a zero-velocity or bias
measurement, a levelling) compiled to machine code.

These updates run ten to a hundred times per second and in numpy each is some twenty calls on
tiny arrays whose Python wrappers cost more than their arithmetic. Compiled with numba the same
operations run in one call, in the same order (the matrix products through the same BLAS
routines), so the filter's numbers do not change; ``kalman.ekf_update`` stays the one entry point,
its numpy path for what this one does not take (a test holds the two together where both apply).
The heading gauge's transfer after an update with a map (:func:`gauge_transfer`) is here too: a rank-two
change of the whole covariance, one pass compiled where numpy makes six. Cached and loaded as
``inertial.propagation_kernel``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

ACCEPTED, SINGULAR, NON_FINITE, GATED = 0, 1, 2, 3


@numba.njit(cache=True, nogil=True)
def small_inverse(S: np.ndarray) -> tuple[bool, np.ndarray, np.ndarray]:
    """``(ok, S⁻¹, L⁻¹)`` of an m × m covariance, m ≤ 3, through its Cholesky factor in scalars; ok is False
    (and the matrices not to be used) where S is not positive definite. A GPS fix's 3 × 3 costs a fraction of
    the general path's four LAPACK calls."""
    m = S.shape[0]
    inv_l = np.zeros((m, m))
    a = S[0, 0]
    if not (a > 0.0 and math.isfinite(a)):
        return False, inv_l, inv_l
    l00 = math.sqrt(a)
    i00 = 1.0 / l00
    inv_l[0, 0] = i00
    if m == 1:
        return True, inv_l * i00, inv_l
    l10 = S[1, 0] / l00
    d = S[1, 1] - l10 * l10
    if not (d > 0.0 and math.isfinite(d)):
        return False, inv_l, inv_l
    l11 = math.sqrt(d)
    i11 = 1.0 / l11
    i10 = -l10 * i00 * i11
    inv_l[1, 0], inv_l[1, 1] = i10, i11
    if m == 2:
        return True, np.dot(inv_l.T.copy(), inv_l), inv_l
    l20 = S[2, 0] / l00
    l21 = (S[2, 1] - l20 * l10) / l11
    d = S[2, 2] - l20 * l20 - l21 * l21
    if not (d > 0.0 and math.isfinite(d)):
        return False, inv_l, inv_l
    i22 = 1.0 / math.sqrt(d)
    i21 = -l21 * i11 * i22
    i20 = -(l20 * i00 + l21 * i10) * i22
    inv_l[2, 0], inv_l[2, 1], inv_l[2, 2] = i20, i21, i22
    return True, np.dot(inv_l.T.copy(), inv_l), inv_l


@numba.njit(cache=True, nogil=True)
def small_update(cov: np.ndarray, c0: int, c1: int, H: np.ndarray, residual: np.ndarray, R: np.ndarray,
                 gate: float, held: np.ndarray) -> tuple[int, float, np.ndarray]:
    """Fuse an m ≤ 3 row measurement whose Jacobian ``H`` covers columns ``c0:c1`` into ``cov`` (in place).

    ``gate``: NIS limit (inf for none); ``held``: a mask over the error state (empty for none), whose
    states get no correction (Joseph-equivalent form). Returns (outcome code, NIS, correction δx).
    """
    n = cov.shape[0]
    m = residual.shape[0]
    PHt = np.dot(np.ascontiguousarray(cov[:, c0:c1]), np.ascontiguousarray(H.T))  # (n, m)
    S = np.dot(H, np.ascontiguousarray(PHt[c0:c1])) + R
    S = 0.5 * (S + S.T)
    ok, S_inv, L_inv = small_inverse(S)
    dx = np.zeros(n)
    if not ok:
        return SINGULAR, math.nan, dx
    for i in range(m):
        if not math.isfinite(residual[i]):
            return NON_FINITE, math.nan, dx
    w = np.dot(L_inv, residual)
    nis = np.dot(w, w)
    if nis > gate:
        return GATED, nis, dx
    K = np.dot(PHt, S_inv)
    if held.shape[0] > 0:
        for i in range(n):
            if held[i]:
                K[i, :] = 0.0
        KPHt = np.dot(K, np.ascontiguousarray(PHt.T))
        cov -= KPHt + KPHt.T - np.dot(np.dot(K, S), np.ascontiguousarray(K.T))
    else:
        cov -= np.dot(K, np.ascontiguousarray(PHt.T))
    cov[...] = 0.5 * (cov + cov.T)
    return ACCEPTED, nis, np.dot(K, residual)


@numba.njit(cache=True, nogil=True)
def gauge_transfer(cov: np.ndarray, d: np.ndarray, yaw: int) -> None:
    """``P ← T P Tᵀ`` with ``T = I + d e_yawᵀ``, in place (``covariance.transfer_gauge``, after a camera update or a
    fix with a map): the same products and sums per element as numpy's three outer products, in one pass over
    the covariance instead of six (a 50-landmark map's 315 × 315 in 0.07 ms instead of 1.4)."""
    c = cov[:, yaw].copy()
    s = cov[yaw, yaw]
    cov += (d[:, None] * c[None, :] + c[:, None] * d[None, :]) + s * (d[:, None] * d[None, :])


NO_HELD = np.zeros(0, dtype=np.bool_)


def warm_up() -> None:
    """Compile (or load from the cache) for the argument types the filter passes, m = 1..3."""
    for m in (1, 2, 3):
        small_inverse(np.eye(m))  # the numpy update's, on its own
        cov = np.eye(15)
        small_update(cov, 0, 9, np.ones((m, 9)), np.zeros(m), np.eye(m), math.inf, NO_HELD)
        small_update(cov, 0, 9, np.ones((m, 9)), np.zeros(m), np.eye(m), 16.0, np.zeros(15, dtype=np.bool_))
    gauge_transfer(np.eye(21), np.zeros(21), 8)
