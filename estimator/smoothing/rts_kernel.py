"""The RTS backward recursion compiled to machine code.

The backward pass walks every filter step from the newest to the oldest, two small matrix
products each; in numpy those products' Python wrappers cost more than their arithmetic, and
since the replay itself became faster the backward pass was the slower half of ``replay
--smooth``. Compiled with numba the same products run through the same BLAS routines in the
same order: the result is bit for bit that of ``rts.recursion``, its numpy reference (a test
holds them together). Cached and loaded as ``inertial.propagation_kernel``.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def recursion(C: np.ndarray, D: np.ndarray, u: np.ndarray, P: np.ndarray, transition: np.ndarray,
              e: np.ndarray, Ps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """See ``rts.recursion``; ``e``/``Ps`` are zeros when there is no later step (the newest step then
    has no transition and restarts the recursion before they are read)."""
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


def warm_up() -> None:
    """Compile (or load from the cache) for the argument types the backward pass passes."""
    for n in (9, 15):
        recursion(np.zeros((2, n, n)), np.zeros((2, n, n)), np.zeros((2, n)), np.zeros((2, n, n)),
                  np.array([True, False]), np.zeros(n), np.zeros((n, n)))
