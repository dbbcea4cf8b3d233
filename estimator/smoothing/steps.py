"""One record per filter step: what a Rauch–Tung–Striebel backward pass needs, robot block only.

A step ``k`` holds the posterior at ``t_k`` (nominal ``x_k``, robot error covariance ``P_k``,
after every measurement at ``t_k``), the error-state transition ``F_k`` of the propagation to
``t_{k+1}``, and the prediction there (``x⁻_{k+1}``, ``P⁻_{k+1}``), before any measurement at
``t_{k+1}``. The last step of a segment has no transition (``t_next_ns < 0``): its posterior is
where the backward pass starts. Nominal vectors are ``[p, v, q (w first), b_g, b_a]``.

Each step also says whether the filter's heading was known: while it is not, the filter works
in a frame of arbitrary yaw (its yaw variance is a gauge, zero), and every smoothed pose of that
stretch is published, like the filtered one, with the variance of a heading anywhere on the circle.

Landmarks are marginalised out: ``P`` is the robot block of the filter's covariance, ``F`` the
robot-to-robot transition (a propagation leaves landmarks alone). See docs/smoothing.md for
what that costs against the full-state smoother.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from vtolpose.estimator.core.state import FilterState

NOMINAL = 16  # p (3), v (3), q (4), b_g (3), b_a (3)
P_, V_, Q_, BG_, BA_ = slice(0, 3), slice(3, 6), slice(6, 10), slice(10, 13), slice(13, 16)


def pack_nominal(state: FilterState) -> np.ndarray:
    return np.concatenate((state.p, state.v, state.q, state.b_g, state.b_a))


@dataclass(slots=True)
class Step:
    segment: int
    t_ns: int
    x: np.ndarray  # (16,) posterior nominal at t_ns
    P: np.ndarray  # (n, n) posterior robot covariance at t_ns
    t_next_ns: int = -1  # < 0: the segment ends here (no transition follows)
    F: np.ndarray | None = None  # (n, n) error-state transition to t_next_ns
    x_pred: np.ndarray | None = None  # (16,) predicted nominal at t_next_ns
    P_pred: np.ndarray | None = None  # (n, n) predicted robot covariance at t_next_ns
    heading_known: bool = True  # False: the filter's yaw is arbitrary (see the module docstring)

    @property
    def ends_segment(self) -> bool:
        return self.t_next_ns < 0


@dataclass(slots=True)
class StepChunk:
    """Consecutive steps as arrays (K steps of robot dimension n); end steps have zero F and prediction."""

    segment: np.ndarray  # (K,) int64
    t_ns: np.ndarray  # (K,) int64
    t_next_ns: np.ndarray  # (K,) int64, < 0 where a segment ends
    x: np.ndarray  # (K, 16)
    P: np.ndarray  # (K, n, n)
    F: np.ndarray  # (K, n, n)
    x_pred: np.ndarray  # (K, 16)
    P_pred: np.ndarray  # (K, n, n)
    heading_known: np.ndarray  # (K,) bool

    FIELDS = ("segment", "t_ns", "t_next_ns", "x", "P", "F", "x_pred", "P_pred", "heading_known")

    def __len__(self) -> int:
        return int(self.t_ns.size)

    @property
    def dim(self) -> int:
        return int(self.P.shape[1])

    @classmethod
    def empty(cls, capacity: int, n: int) -> "StepChunk":
        return cls(np.zeros(capacity, np.int64), np.zeros(capacity, np.int64), np.full(capacity, -1, np.int64),
                   np.zeros((capacity, NOMINAL)), np.zeros((capacity, n, n)), np.zeros((capacity, n, n)),
                   np.zeros((capacity, NOMINAL)), np.zeros((capacity, n, n)), np.ones(capacity, dtype=bool))

    def head(self, k: int) -> "StepChunk":
        return StepChunk(*(getattr(self, name)[:k] for name in self.FIELDS))

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in self.FIELDS}


class ChunkBuilder:
    """Collects steps into chunks of ``chunk_steps``; hands each full one (and the last, on
    :meth:`flush`) to ``emit``. Memory: one chunk, whatever the flight's length."""

    def __init__(self, emit: Callable[[StepChunk], None], chunk_steps: int = 2048) -> None:
        if chunk_steps < 1:
            raise ValueError(f"chunk_steps must be at least 1, got {chunk_steps}")
        self.emit = emit
        self.chunk_steps = chunk_steps
        self._chunk: StepChunk | None = None
        self._k = 0
        self.steps = 0

    def add(self, step: Step) -> None:
        chunk = self._chunk
        if chunk is None:
            chunk = self._chunk = StepChunk.empty(self.chunk_steps, step.P.shape[0])
        k = self._k
        chunk.segment[k], chunk.t_ns[k], chunk.t_next_ns[k] = step.segment, step.t_ns, step.t_next_ns
        chunk.x[k], chunk.P[k], chunk.heading_known[k] = step.x, step.P, step.heading_known
        if not step.ends_segment:
            chunk.F[k], chunk.x_pred[k], chunk.P_pred[k] = step.F, step.x_pred, step.P_pred
        self._k += 1
        self.steps += 1
        if self._k == self.chunk_steps:
            self.flush()

    def flush(self) -> None:
        if self._chunk is not None and self._k:
            self.emit(self._chunk.head(self._k))
        self._chunk, self._k = None, 0
