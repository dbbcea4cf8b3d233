"""The EKF measurement update, shared by every updater (GPS, camera, …).

Measurement Jacobians are usually sparse in columns (a GPS fix touches the robot block, a
landmark observation the robot block and six landmark columns), so an updater passes only
the columns it touches. Optionally some states are *held*: they get no correction and their
covariance stays as it was, but cross-covariances are kept consistent (Schmidt–Kalman).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from vtolpose.estimator.core import update_kernel
from vtolpose.estimator.core.chi2 import upper_quantile
from vtolpose.estimator.core.state import FilterState


@lru_cache(maxsize=64)
def chi2_gate(dof: int, probability: float = 0.95) -> float:
    """Upper χ² quantile: innovations with NIS above it are outliers at this confidence."""
    return upper_quantile(dof, 1.0 - probability)


@dataclass(frozen=True, slots=True)
class UpdateOutcome:
    accepted: bool
    nis: float
    dof: int
    reason: str = ""


def _cholesky(S: np.ndarray) -> np.ndarray | None:
    try:
        return np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        return None


def innovation_covariance(state: FilterState, cols: np.ndarray | slice, H: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``S = H P H^T + R`` for a Jacobian that is non-zero only in ``cols``."""
    block = state.cov[cols, cols] if isinstance(cols, slice) else state.cov[np.ix_(cols, cols)]
    return H @ block @ H.T + R


def normalized_innovation(S: np.ndarray, residual: np.ndarray) -> float | None:
    """NIS ``ε^T S^-1 ε``, or None when S is not positive definite."""
    L = _cholesky(S)
    if L is None:
        return None
    w = np.linalg.solve(L, residual)
    return float(w @ w)


def ekf_update(
    state: FilterState,
    cols: np.ndarray | slice,
    H: np.ndarray,
    residual: np.ndarray,
    R: np.ndarray,
    gate: float | None = None,
    held: np.ndarray | None = None,
) -> UpdateOutcome:
    """Fuse one (possibly stacked) measurement into ``state``.

    ``H`` has shape (m, len(cols)). ``gate`` is the NIS threshold; a measurement beyond it is
    rejected and the state is untouched. ``held`` is a boolean mask over the error state of
    states that must not be corrected.
    """
    if residual.shape[0] <= 3 and isinstance(cols, slice) and cols.step in (None, 1) and state.cov.flags.c_contiguous:
        return _compiled_update(state, cols, H, residual, R, gate, held)
    return _numpy_update(state, cols, H, residual, R, gate, held)


def _numpy_update(state: FilterState, cols: np.ndarray | slice, H: np.ndarray, residual: np.ndarray, R: np.ndarray,
                  gate: float | None, held: np.ndarray | None) -> UpdateOutcome:
    """:func:`ekf_update` in numpy, for what the compiled update does not take: stacked measurements (more than
    three rows), scattered columns (a landmark's observation: the robot block and the landmark's six), a
    covariance that is not C-ordered. Not a twin: the compiled path declines these; where both apply, a test
    holds them to the same bits. A small S is still inverted by the compiled ``update_kernel.small_inverse``."""
    m = residual.shape[0]
    cov = state.cov
    PHt = cov[:, cols] @ H.T  # (n, m)
    S = H @ PHt[cols] + R
    S = 0.5 * (S + S.T)
    if m <= 3:
        positive, S_inv, L_inv = update_kernel.small_inverse(S)
        if not positive or not all(math.isfinite(x) for x in residual.tolist()):
            return UpdateOutcome(False, float("nan"), m,
                                 "non-finite residual" if positive else "singular innovation covariance")
        w = L_inv @ residual
        nis = float(w @ w)
        if gate is not None and nis > gate:
            return UpdateOutcome(False, nis, m, "chi2 gate")
        K = PHt @ S_inv
    else:
        L = _cholesky(S)
        if L is None or not np.all(np.isfinite(residual)):
            return UpdateOutcome(False, float("nan"), m, "singular innovation covariance" if L is None else "non-finite residual")
        w = np.linalg.solve(L, residual)
        nis = float(w @ w)
        if gate is not None and nis > gate:
            return UpdateOutcome(False, nis, m, "chi2 gate")
        # K = PHt S^-1, computed through the Cholesky factor.
        K = np.linalg.solve(L.T, np.linalg.solve(L, PHt.T)).T
    if held is not None:
        K[held] = 0.0
        # Joseph-equivalent form for a suboptimal gain that leaves held states alone.
        KPHt = K @ PHt.T
        cov -= KPHt + KPHt.T - K @ S @ K.T
    else:
        cov -= K @ PHt.T
    cov[...] = 0.5 * (cov + cov.T)
    state.inject(K @ residual)
    if state.observer is not None:
        state.observer.updated(state)
    return UpdateOutcome(True, nis, m)


REASONS = {1: "singular innovation covariance", 2: "non-finite residual", 3: "chi2 gate"}


def _compiled_update(state: FilterState, cols: slice, H: np.ndarray, residual: np.ndarray, R: np.ndarray,
                     gate: float | None, held: np.ndarray | None) -> UpdateOutcome:
    """:func:`ekf_update` for one to three rows on a column range, in one compiled call (``update_kernel``);
    the arrays made C-ordered and float so that one machine-code version serves every caller."""
    start, stop, _ = cols.indices(state.cov.shape[0])
    code, nis, dx = update_kernel.small_update(
        state.cov, start, stop, np.ascontiguousarray(H, dtype=float), np.ascontiguousarray(residual, dtype=float),
        np.ascontiguousarray(R, dtype=float), math.inf if gate is None else float(gate),
        update_kernel.NO_HELD if held is None else np.ascontiguousarray(held, dtype=np.bool_))
    return compiled_outcome(state, code, nis, dx, residual.shape[0])


def compiled_outcome(state: FilterState, code: int, nis: float, dx: np.ndarray, m: int) -> UpdateOutcome:
    """What a compiled update's (code, NIS, δx) mean for ``state``: the correction folded in when accepted."""
    if code:
        return UpdateOutcome(False, float(nis), m, REASONS[code])
    state.inject(dx)
    if state.observer is not None:
        state.observer.updated(state)
    return UpdateOutcome(True, float(nis), m)
