"""A GPS fix's whole EKF update in one compiled call: lever arm, residual, Jacobian, noise and the update, for
the filter's state or for every heading hypothesis at once (with what a hypothesis' weight needs); for the
filter without a map (:func:`filter_fix`) with the noise check's innovation, the injection and the residual
after the update as well.

In Python the fix costs a dozen calls on three-element arrays (rotation, lever arm, prediction,
Jacobian, noise, each wrapper dearer than its arithmetic) around the compiled update. Here the same
operations run in one call, in the same order and on the same formulas as
:class:`~vtolpose.estimator.gnss.gps_update.GpsModel` and
:func:`~vtolpose.estimator.core.update_kernel.small_update`, so the filter's numbers do not change (a
test holds the two paths bit for bit). Cached and loaded as the other kernels are
(``service.runtime.kernels.load_compiled_kernels``).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vtolpose.estimator.core.rotation import compiled_quat_product as quat_product
from vtolpose.estimator.core.rotation import compiled_rot_of as rot_of
from vtolpose.estimator.core.rotation import compiled_rotvec_quat as rotvec_quat
from vtolpose.estimator.core.update_kernel import NO_HELD, small_update

NAV_DIM = 9  # δp, δv, δθ: the error states a fix depends on


@numba.njit(cache=True, nogil=True)
def lever_arm_world(q: np.ndarray, lever_b: np.ndarray) -> np.ndarray:
    """``R(q) l``: the rotation as :func:`~vtolpose.estimator.core.rotation.rot_of` builds it, then the product."""
    r = np.empty((3, 3))
    (r[0, 0], r[0, 1], r[0, 2]), (r[1, 0], r[1, 1], r[1, 2]), (r[2, 0], r[2, 1], r[2, 2]) = rot_of(q[0], q[1], q[2], q[3])
    return np.dot(r, lever_b)


@numba.njit(cache=True, nogil=True)
def fix_model(p: np.ndarray, q: np.ndarray, lever_b: np.ndarray, fix: np.ndarray, var_h: float,
              var_v: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A fix's residual, Jacobian on [δp, δv, δθ] and noise, as ``GpsModel`` and ``GpsUpdater.noise`` give them."""
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
    return residual, H, R


@numba.njit(cache=True, nogil=True)
def innovation_log_det(cov: np.ndarray, H: np.ndarray, R: np.ndarray) -> float:
    """``log det(H P H^T + R)`` over the first nine error states, through its Cholesky factor; -inf where the
    innovation covariance is not positive definite (a likelihood of zero)."""
    S = np.dot(np.dot(H, np.ascontiguousarray(cov[:NAV_DIM, :NAV_DIM])), np.ascontiguousarray(H.T)) + R
    log_det = 0.0
    L = np.zeros((3, 3))
    for i in range(3):
        for j in range(i + 1):
            acc = S[i, j]
            for m in range(j):
                acc -= L[i, m] * L[j, m]
            if i == j:
                if not (acc > 0.0 and math.isfinite(acc)):
                    return -math.inf
                L[i, i] = math.sqrt(acc)
                log_det += math.log(acc)
            else:
                L[i, j] = acc / L[j, j]
    return log_det


@numba.njit(cache=True, nogil=True)
def gps_update(p: np.ndarray, v: np.ndarray, q: np.ndarray, b_g: np.ndarray, b_a: np.ndarray, covs: np.ndarray,
               fold_in: bool, biases: bool, lever_b: np.ndarray, fix: np.ndarray, var_h: float, var_v: float,
               gate: float, held: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fuse a fix ``fix`` (NED, m) with variances ``var_h``, ``var_h``, ``var_v``, the antenna ``lever_b`` from
    the IMU, into each of a stack of states (rows of ``p`` … ``covs``; the covariances change in place).

    Returns per state a row of (``small_update``'s outcome code, NIS, ``log det S`` before the update, 1.0 if
    it came out accepted and finite else 0.0) and its correction δx: two arrays, for each one returned costs.

    ``fold_in`` (the heading hypotheses, robot states only): the corrections are folded into the rows of
    ``p``, ``v``, ``q`` (and ``b_g``, ``b_a`` with ``biases``) as ``FilterState.inject`` does, and the
    log-determinants and finiteness worked out. Otherwise (the filter: one state, a map perhaps) the nominal
    rows are only read, the caller folds δx in, and the log-determinants stay -inf."""
    k = p.shape[0]
    info = np.empty((k, 4))
    dxs = np.empty((k, covs.shape[1]))
    for j in range(k):
        cov = covs[j]
        residual, H, R = fix_model(p[j], q[j], lever_b, fix, var_h, var_v)
        # A hypothesis' weight needs the log-determinant, the filter does not.
        log_det = innovation_log_det(cov, H, R) if fold_in else -math.inf
        code, nis, dx = small_update(cov, 0, 9, H, residual, R, gate, held)
        info[j, 0], info[j, 1], info[j, 2], info[j, 3] = code, nis, log_det, 0.0
        dxs[j] = dx
        if code != 0 or not fold_in:
            continue
        for i in range(3):
            p[j, i] = p[j, i] + dx[i]
            v[j, i] = v[j, i] + dx[3 + i]
        # Exp(δθ) ⊗ q, then normalised (FilterState.inject with rotation.rotvec_quat).
        dw, ex, ey, ez = rotvec_quat(dx[6], dx[7], dx[8])
        r0, r1, r2, r3 = quat_product(dw, ex, ey, ez, q[j, 0], q[j, 1], q[j, 2], q[j, 3])
        norm = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2 + r3 * r3)
        q[j, 0], q[j, 1], q[j, 2], q[j, 3] = r0 / norm, r1 / norm, r2 / norm, r3 / norm
        if biases:
            for i in range(3):
                b_g[j, i] = b_g[j, i] + dx[9 + i]
                b_a[j, i] = b_a[j, i] + dx[12 + i]
        finite = math.isfinite(log_det)
        for i in range(3):
            finite = finite and math.isfinite(p[j, i]) and math.isfinite(v[j, i]) and math.isfinite(b_g[j, i]) \
                and math.isfinite(b_a[j, i])
        for i in range(4):
            finite = finite and math.isfinite(q[j, i])
        for a in range(cov.shape[0]):
            for b in range(cov.shape[1]):
                finite = finite and math.isfinite(cov[a, b])
        info[j, 3] = 1.0 if finite else 0.0
    return info, dxs


FIX_INFO = 9  # filter_fix's row: code, NIS, the noise check's NIS, its innovation (3), the posterior residual (3)


@numba.njit(cache=True, nogil=True)
def claimed_nis(cov: np.ndarray, H: np.ndarray, residual: np.ndarray, var_h: float, var_v: float) -> float:
    """``ν^T (H P H^T + diag(σ_h², σ_h², σ_v²))⁻¹ ν`` as ``GpsNoiseCheck.before_update`` has it (a solve, not a
    Cholesky factor: the claimed noise may be anything); inf where that matrix is singular."""
    S = np.dot(np.dot(H, np.ascontiguousarray(cov[:NAV_DIM, :NAV_DIM])), np.ascontiguousarray(H.T))
    S[0, 0] += var_h
    S[1, 1] += var_h
    S[2, 2] += var_v
    try:
        return np.dot(residual, np.linalg.solve(S, residual))
    except Exception:  # numpy's LinAlgError: an exactly singular matrix
        return math.inf


@numba.njit(cache=True, nogil=True)
def filter_fix(p: np.ndarray, v: np.ndarray, q: np.ndarray, b_g: np.ndarray, b_a: np.ndarray, cov: np.ndarray,
               biases: bool, lever_b: np.ndarray, fix: np.ndarray, var_h: float, var_v: float, gate: float,
               check: bool, claim_h: float, claim_v: float) -> tuple[np.ndarray, ...]:
    """A fix fused into the filter's state without a map: what ``GpsNoiseCheck.before_update``, ``GpsUpdater.update``,
    ``FilterState.inject`` and the posterior ``GpsUpdater.residual`` do in Python, in one call.

    ``cov`` changes in place; the nominal parts come back as new arrays (a pose keeps the old ones) with the row
    :data:`FIX_INFO`: ``small_update``'s code and NIS, then with ``check`` the NIS under the claimed variances
    ``claim_h``, ``claim_v`` (else NaN), the innovation and the residual after the update."""
    info = np.full(FIX_INFO, math.nan)
    residual, H, R = fix_model(p, q, lever_b, fix, var_h, var_v)
    if check:
        info[2] = claimed_nis(cov, H, residual, claim_h, claim_v)
    info[3:6] = residual
    code, nis, dx = small_update(cov, 0, NAV_DIM, H, residual, R, gate, NO_HELD)
    info[0], info[1] = code, nis
    p, v, q, b_g, b_a = p.copy(), v.copy(), q.copy(), b_g.copy(), b_a.copy()
    if code == 0:
        for i in range(3):
            p[i] = p[i] + dx[i]
            v[i] = v[i] + dx[3 + i]
        dw, ex, ey, ez = rotvec_quat(dx[6], dx[7], dx[8])
        r0, r1, r2, r3 = quat_product(dw, ex, ey, ez, q[0], q[1], q[2], q[3])
        norm = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2 + r3 * r3)
        q[0], q[1], q[2], q[3] = r0 / norm, r1 / norm, r2 / norm, r3 / norm
        if biases:
            for i in range(3):
                b_g[i] = b_g[i] + dx[9 + i]
                b_a[i] = b_a[i] + dx[12 + i]
    info[6:9] = fix - (p + lever_arm_world(q, lever_b))
    return info, p, v, q, b_g, b_a


def warm_up() -> None:
    """Compile (or load from the cache) for the argument types the filter and the heading hypotheses pass (a
    mask of held states, or none, is the same type)."""
    stack = np.zeros((2, 3))
    gps_update(stack, stack.copy(), np.tile([1.0, 0.0, 0.0, 0.0], (2, 1)), stack.copy(), stack.copy(),
               np.stack([np.eye(15)] * 2), True, True, np.zeros(3), np.zeros(3), 1.0, 2.0, math.inf, NO_HELD)
    for dim in (9, 15):  # the two models' states
        filter_fix(np.zeros(3), np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3), np.zeros(3), np.eye(dim),
                   dim == 15, np.zeros(3), np.zeros(3), 1.0, 2.0, math.inf, True, 1.0, 2.0)
