"""The RTS backward recursion written plainly in numpy: the oracle the compiled one (``rts_kernel.recursion``,
``rts_kernel.backward_step``) is tested against, bit for bit; itself tested against batch least squares
(tests/test_smoothing.py). The runtime runs only the compiled one."""

from __future__ import annotations

import numpy as np


def backward_step(C: np.ndarray, D: np.ndarray, u: np.ndarray, e_next: np.ndarray,
                  Ps_next: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One RTS step on the corrections: ``(e_k, Pˢ_k)`` from ``(e_{k+1}, Pˢ_{k+1})``."""
    return C @ (e_next + u), C @ Ps_next @ C.T + D


def recursion(C: np.ndarray, D: np.ndarray, u: np.ndarray, P: np.ndarray, transition: np.ndarray,
              e: np.ndarray | None, Ps: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The linear heart of the pass over K steps, newest last: corrections ``e_k`` and ``Pˢ_k`` for each.

    A step without ``transition`` restarts the recursion at its posterior (``e = 0``, ``Pˢ = P``);
    ``e``/``Ps`` carry the estimate of the step after the last one (None if there is none).
    """
    k_total, n = u.shape
    e_out, P_out = np.empty((k_total, n)), np.empty((k_total, n, n))
    zero = np.zeros(n)
    for k in range(k_total - 1, -1, -1):
        if transition[k]:
            Ck = C[k]
            e, Ps = Ck @ (e + u[k]), Ck @ Ps @ Ck.T + D[k]
        else:
            e, Ps = zero, P[k]
        e_out[k], P_out[k] = e, Ps
    return e_out, P_out, e, Ps
