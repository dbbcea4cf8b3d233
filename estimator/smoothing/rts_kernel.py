"""The RTS backward recursion compiled to machine code.

The backward pass walks every filter step from the newest to the oldest, two small matrix
products each; in numpy those products' Python wrappers cost more than their arithmetic, enough
to make the backward pass the slower half of ``replay --smooth``. Compiled with numba the same
products run through the same BLAS routines in the same order: the result is bit for bit that of
the same recursion written in numpy (tests/rts_oracle.py, the oracle a test holds it to). Cached
and loaded as ``inertial.propagation_kernel``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vtolpose.estimator.core.rotation import compiled_quat_exp_of as quat_exp_of
from vtolpose.estimator.core.rotation import compiled_quat_product as quat_product


@numba.njit(cache=True, nogil=True)
def recursion(C: np.ndarray, D: np.ndarray, u: np.ndarray, P: np.ndarray, transition: np.ndarray,
              e: np.ndarray, Ps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The linear heart of the pass over K steps, newest last: corrections ``e_k`` and ``Pˢ_k`` for each
    (``rts``'s module docstring). A step without ``transition`` restarts the recursion at its posterior
    (``e = 0``, ``Pˢ = P``); ``e``/``Ps`` carry the estimate of the step after the last one, zeros when there
    is none (the newest step then has no transition and restarts the recursion before they are read)."""
    k_total, n = u.shape
    e_out, P_out = np.empty((k_total, n)), np.empty((k_total, n, n))
    zero = np.zeros(n)
    for k in range(k_total - 1, -1, -1):
        if transition[k]:
            Ck = np.ascontiguousarray(C[k])
            e, Ps = np.dot(Ck, e + u[k]), np.dot(np.dot(Ck, Ps), np.ascontiguousarray(Ck.T)) + D[k]
        else:
            e, Ps = zero, np.ascontiguousarray(P[k])
        e_out[k], P_out[k] = e, Ps
    return e_out, P_out, e, Ps


@numba.njit(cache=True, nogil=True)
def gains(P: np.ndarray, F: np.ndarray, P_pred: np.ndarray, transition: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``rts.gains`` for each step with a transition (zeros elsewhere): the same scaling and products, but the
    scaled prediction (symmetric positive definite) solved through its Cholesky factor, written out so that
    each row works on all right-hand sides at once (cheaper than LAPACK's general solve at n = 15); equal to
    round-off. Raises ``LinAlgError`` where a scaled prediction is not positive definite (``rts.gains``,
    with its least-squares way, then takes over)."""
    k_total, n = P.shape[0], P.shape[1]
    C_out, D_out = np.zeros((k_total, n, n)), np.zeros((k_total, n, n))
    s = np.empty(n)
    L = np.zeros((n, n))
    Z = np.empty((n, n))
    for k in range(k_total):
        if not transition[k]:
            continue
        Pk = np.ascontiguousarray(P[k])
        FP = np.dot(np.ascontiguousarray(F[k]), Pk)
        Pp = P_pred[k]
        for i in range(n):
            s[i] = 1.0 / math.sqrt(max(Pp[i, i], 1e-300))
        for j in range(n):  # L Lᵀ = diag(s) P⁻ diag(s)
            d = Pp[j, j] * s[j] * s[j]
            for m in range(j):
                d -= L[j, m] * L[j, m]
            if not d > 0.0:
                raise np.linalg.LinAlgError("a scaled prediction is not positive definite")
            ljj = math.sqrt(d)
            L[j, j] = ljj
            for i in range(j + 1, n):
                a = Pp[i, j] * s[i] * s[j]
                for m in range(j):
                    a -= L[i, m] * L[j, m]
                L[i, j] = a / ljj
        for i in range(n):  # L Y = diag(s) F P, row by row
            si = s[i]
            for c in range(n):
                Z[i, c] = FP[i, c] * si
            for m in range(i):
                lim = L[i, m]
                for c in range(n):
                    Z[i, c] -= lim * Z[m, c]
            inv = 1.0 / L[i, i]
            for c in range(n):
                Z[i, c] *= inv
        for i in range(n - 1, -1, -1):  # Lᵀ Z = Y
            for m in range(i + 1, n):
                lmi = L[m, i]
                for c in range(n):
                    Z[i, c] -= lmi * Z[m, c]
            inv = 1.0 / L[i, i]
            for c in range(n):
                Z[i, c] *= inv
        C = C_out[k]
        for i in range(n):
            si = s[i]
            for j in range(n):
                C[j, i] = Z[i, j] * si
        CFP = np.dot(C, FP)
        D = D_out[k]
        for i in range(n):
            for j in range(n):
                D[i, j] = 0.5 * ((Pk[i, j] - CFP[i, j]) + (Pk[j, i] - CFP[j, i]))
    return C_out, D_out


@numba.njit(cache=True, nogil=True)
def backward_step(C: np.ndarray, D: np.ndarray, u: np.ndarray, e_next: np.ndarray,
                  Ps_next: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One RTS step on the corrections, ``(e_k, Pˢ_k)`` from ``(e_{k+1}, Pˢ_{k+1})``: the fixed-lag smoother's sweep."""
    return np.dot(C, e_next + u), np.dot(np.dot(C, Ps_next), np.ascontiguousarray(C.T)) + D


@numba.njit(cache=True, nogil=True, error_model="numpy")  # a zero quaternion gives NaN, as in numpy, not an exception
def apply_error(x: np.ndarray, dx: np.ndarray, n: int) -> np.ndarray:
    """``rts.apply_error`` for one nominal vector (16) and one error (n), bit for bit: ``x ⊞ dx``."""
    out = x.copy()
    for i in range(6):
        out[i] += dx[i]
    pw, px, py, pz = quat_exp_of(dx[6], dx[7], dx[8])
    w, a, b, c = quat_product(pw, px, py, pz, x[6], x[7], x[8], x[9])
    norm = math.sqrt(w * w + a * a + b * b + c * c)
    out[6], out[7], out[8], out[9] = w / norm, a / norm, b / norm, c / norm
    if n > 9:
        for i in range(6):
            out[10 + i] += dx[9 + i]
    return out


def warm_up(backward_pass: bool = False) -> None:
    """Compile (or load from the cache) for the argument types the smoothers pass: the fixed-lag smoother's
    kernels, and with ``backward_pass`` the whole-flight pass's recursion too (only ``replay --smooth`` runs
    it, after the replay, where loading it on first use costs nothing; each kernel loaded costs ~1–4 MB)."""
    for n in (9, 15):
        if backward_pass:
            recursion(np.zeros((2, n, n)), np.zeros((2, n, n)), np.zeros((2, n)), np.zeros((2, n, n)),
                      np.array([True, False]), np.zeros(n), np.zeros((n, n)))
        gains(np.zeros((2, n, n)), np.zeros((2, n, n)), np.stack([np.eye(n)] * 2), np.array([True, False]))
        backward_step(np.eye(n), np.eye(n), np.zeros(n), np.zeros(n), np.eye(n))
        apply_error(np.array([0.0] * 6 + [1.0] + [0.0] * 9), np.zeros(n), n)
