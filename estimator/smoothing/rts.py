"""The Rauch–Tung–Striebel backward pass over recorded steps, on the robot error state.

For a step ``k`` (posterior ``x_k, P_k``; transition ``F_k``; prediction ``x⁻_{k+1}, P⁻_{k+1}``)
and the smoothed estimate at ``k+1`` (``xˢ_{k+1}, Pˢ_{k+1}``)::

    C_k   = P_k F_kᵀ (P⁻_{k+1})⁻¹
    xˢ_k  = x_k ⊞ C_k (xˢ_{k+1} ⊟ x⁻_{k+1})
    Pˢ_k  = P_k + C_k (Pˢ_{k+1} − P⁻_{k+1}) C_kᵀ  =  C_k Pˢ_{k+1} C_kᵀ + (P_k − C_k F_k P_k)

``⊟``/``⊞`` are the filter's error-state conventions (``FilterState.inject``): differences for
position, velocity and biases, a world-frame rotation vector for the attitude
(``R = Exp(δθ) R̂``). Biases are smoothed like everything else.

The recursion runs on the smoothed correction ``e_k = xˢ_k ⊟ x_k`` of each posterior:
``xˢ_{k+1} ⊟ x⁻_{k+1} = e_{k+1} + u_{k+1}`` with ``u_{k+1} = x_{k+1} ⊟ x⁻_{k+1}`` (what the
measurements at ``k+1`` corrected), so ``e_k = C_k (e_{k+1} + u_{k+1})``. That sum is exact for
position, velocity and biases; for the attitude it drops the second-order term ``½ e × u`` of
composing two small rotations (below 10⁻⁶ rad for milliradian corrections). In exchange
everything but two small matrix products per step — the gains ``C, D``, the corrections ``u``,
the final ``x ⊞ e`` — is computed for a whole chunk at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vtolpose.estimator.core.rotation import quat_conj, quat_exp, quat_log, quat_mul
from vtolpose.estimator.inertial.heading_bank import UNKNOWN_HEADING_VAR
from vtolpose.estimator.smoothing.steps import NOMINAL, ChunkBuilder, Step, StepChunk
from vtolpose.estimator.smoothing import rts_kernel

POSE_IX = np.r_[0:3, 6:9]  # [δp, δθ] in every robot layout
POSE_YAW = 5  # the heading in the [δp, δθ] pose covariance


def published_pose_cov(pose_cov: np.ndarray, heading_known: np.ndarray | bool) -> np.ndarray:
    """Pose covariances ``(..., 6, 6)`` as the outputs give them: where the heading is not known, the
    filter's yaw is an arbitrary gauge, so it gets the variance of a heading anywhere on the circle,
    uncorrelated with the rest (as ``Estimator.published_cov9`` does for the filtered pose)."""
    unknown = ~np.asarray(heading_known, dtype=bool)
    if not np.any(unknown):
        return pose_cov
    out = np.array(pose_cov, dtype=float)
    sel = out[unknown] if out.ndim == 3 else out
    sel[..., POSE_YAW, :] = 0.0
    sel[..., :, POSE_YAW] = 0.0
    sel[..., POSE_YAW, POSE_YAW] = UNKNOWN_HEADING_VAR
    if out.ndim == 3:
        out[unknown] = sel
    return out


def error_between(x_a: np.ndarray, x_b: np.ndarray, n: int) -> np.ndarray:
    """``x_a ⊟ x_b`` for nominal vectors ``(..., 16)``: the error state (n = 9 or 15) taking ``x_b`` to ``x_a``."""
    d = x_a - x_b
    theta = quat_log(quat_mul(x_a[..., 6:10], quat_conj(x_b[..., 6:10])))
    return np.concatenate([d[..., 0:6], theta] + ([d[..., 10:16]] if n > 9 else []), axis=-1)


def apply_error(x: np.ndarray, dx: np.ndarray, n: int) -> np.ndarray:
    """``x ⊞ dx`` for ``(..., 16)`` and ``(..., n)``, as ``FilterState.inject`` (attitude on the left, world frame)."""
    out = np.array(x, dtype=float)
    out[..., 0:6] += dx[..., 0:6]
    q = quat_mul(quat_exp(dx[..., 6:9]), x[..., 6:10])
    out[..., 6:10] = q / np.linalg.norm(q, axis=-1, keepdims=True)
    if n > 9:
        out[..., 10:16] += dx[..., 9:15]
    return out


def gains(P: np.ndarray, F: np.ndarray, P_pred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RTS gains ``C = P Fᵀ (P⁻)⁻¹`` and ``D = P − C F P`` for stacks ``(..., n, n)``.

    ``P⁻`` is solved after scaling to unit diagonal: its variances span ten orders of magnitude
    (position in cm², gyro bias in (µrad/s)²), its correlations do not.
    """
    FP = F @ P
    s = 1.0 / np.sqrt(np.maximum(np.diagonal(P_pred, axis1=-2, axis2=-1), 1e-300))
    scaled = P_pred * s[..., :, None] * s[..., None, :]
    try:
        Z = np.linalg.solve(scaled, FP * s[..., :, None])
    except np.linalg.LinAlgError:  # a singular prediction somewhere: least squares for the whole stack
        Z = np.linalg.pinv(scaled, hermitian=True) @ (FP * s[..., :, None])
    C = np.swapaxes(Z * s[..., :, None], -1, -2)
    D = P - C @ FP
    return C, 0.5 * (D + np.swapaxes(D, -1, -2))


def stacked_gains(P: np.ndarray, F: np.ndarray, P_pred: np.ndarray, transition: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`gains` for the steps with a ``transition`` (zeros elsewhere): compiled (``rts_kernel.gains``, the
    same scaling, a Cholesky solve: equal to round-off), here where a prediction that is not positive
    definite needs the least-squares way."""
    try:
        return rts_kernel.gains(np.ascontiguousarray(P), np.ascontiguousarray(F), np.ascontiguousarray(P_pred),
                                np.ascontiguousarray(transition))
    except np.linalg.LinAlgError:
        C, D = np.zeros(P.shape), np.zeros(P.shape)
        if np.any(transition):
            C[transition], D[transition] = gains(P[transition], F[transition], P_pred[transition])
        return C, D


@dataclass(slots=True)
class SmoothedChunk:
    """Smoothed estimates in time order: nominal ``[p, v, q, b_g, b_a]`` and the pose covariance."""

    t_ns: np.ndarray  # (K,) int64
    x: np.ndarray  # (K, 16)
    pose_cov: np.ndarray  # (K, 6, 6) over [δp, δθ] (world-frame attitude error)
    vel_var: np.ndarray  # (K, 3)
    segment: np.ndarray  # (K,) int64
    heading_known: np.ndarray  # (K,) bool; where False, pose_cov has the unknown heading's variance

    def __len__(self) -> int:
        return int(self.t_ns.size)

    @property
    def p(self) -> np.ndarray:
        return self.x[:, 0:3]

    @property
    def v(self) -> np.ndarray:
        return self.x[:, 3:6]

    @property
    def q(self) -> np.ndarray:
        return self.x[:, 6:10]


class BackwardPass:
    """Feed :meth:`chunk` the recorded chunks from the newest to the oldest; each call returns that
    chunk's smoothed estimates in time order. Where a segment's end and the next segment's start
    share a time, the later segment's estimate (after the reset) is the one kept."""

    def __init__(self) -> None:
        self._e: np.ndarray | None = None  # smoothed correction of the oldest step done so far
        self._Ps: np.ndarray | None = None
        self._x: np.ndarray | None = None  # that step's posterior (the next older step's successor)
        self._segment: int | None = None
        self._last_t: int | None = None  # the oldest time emitted so far
        self.steps = 0

    def chunk(self, chunk: StepChunk) -> SmoothedChunk:
        k_total, n = len(chunk), chunk.dim
        transition = chunk.t_next_ns >= 0
        u = np.zeros((k_total, n))
        P = np.ascontiguousarray(chunk.P)
        if np.any(transition):
            if transition[-1] and self._x is None:
                raise ValueError("the newest chunk ends inside a segment: the recorder was not finished")
            successor = np.concatenate([chunk.x[1:], [chunk.x[-1] if self._x is None else self._x]])
            u[transition] = error_between(successor[transition], chunk.x_pred[transition], n)
        C, D = stacked_gains(P, chunk.F, chunk.P_pred, transition)
        seg_all, t_all = chunk.segment, chunk.t_ns
        successor_seg = np.concatenate([seg_all[1:], [seg_all[-1] if self._segment is None else self._segment]])
        broken = transition & (successor_seg != seg_all)
        if np.any(broken):
            raise ValueError(f"step at t_ns={int(t_all[np.argmax(broken)])} has no successor in its segment: "
                             "steps out of order")
        n_zero = np.zeros(n)
        e_out, P_out, e, Ps = rts_kernel.recursion(  # compiled (tests/rts_oracle.py is its numpy reading)
            C, D, u, P, np.ascontiguousarray(transition),
            n_zero if self._e is None else self._e, np.zeros((n, n)) if self._Ps is None else self._Ps)
        # Where a segment's end and the next segment's start share a time, keep the later one.
        newest = np.iinfo(np.int64).max if self._last_t is None else self._last_t
        later = np.minimum(np.append(np.minimum.accumulate(t_all[::-1])[::-1][1:], newest), newest)
        keep = t_all < later
        last_t = int(min(t_all.min(), newest))
        self._e, self._Ps, self._x, self._segment, self._last_t = e, Ps, chunk.x[0], int(seg_all[0]), last_t
        self.steps += k_total
        P_out = P_out[keep]
        heading = chunk.heading_known[keep].copy()
        return SmoothedChunk(t_all[keep].copy(), apply_error(chunk.x[keep], e_out[keep], n),
                             published_pose_cov(P_out[:, POSE_IX][:, :, POSE_IX], heading),
                             np.diagonal(P_out, axis1=1, axis2=2)[:, 3:6].copy(), seg_all[keep].copy(), heading)


def concatenate(parts: list[SmoothedChunk]) -> SmoothedChunk:
    """Chunks in time order joined into one."""
    if not parts:
        return SmoothedChunk(np.zeros(0, np.int64), np.zeros((0, NOMINAL)), np.zeros((0, 6, 6)), np.zeros((0, 3)),
                             np.zeros(0, np.int64), np.zeros(0, dtype=bool))
    return SmoothedChunk(*(np.concatenate([getattr(p, name) for p in parts]) for name in
                           ("t_ns", "x", "pose_cov", "vel_var", "segment", "heading_known")))


def smooth_steps(steps: list[Step], chunk_steps: int = 2048) -> SmoothedChunk:
    """The whole backward pass over steps held in memory (short flights, tests)."""
    chunks: list[StepChunk] = []
    builder = ChunkBuilder(chunks.append, chunk_steps)
    for step in steps:
        builder.add(step)
    builder.flush()
    backward = BackwardPass()
    return concatenate([backward.chunk(c) for c in reversed(chunks)][::-1])
