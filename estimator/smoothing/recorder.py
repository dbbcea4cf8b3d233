"""The forward pass's side of smoothing: one :class:`~.steps.Step` per IMU propagation.

The estimator calls :meth:`StepRecorder.before_propagation` and :meth:`after_propagation`
around each covariance propagation, and the shared EKF update
(``vtolpose.estimator.core.kalman.ekf_update``) calls :meth:`updated` after each measurement it
fuses. Those are the only two places where the robot covariance may change inside a segment.

Anything else that changes the robot state or its covariance between two propagations (a
reset, a position re-initialised from GPS, a covariance widened over an IMU gap, a rebuilt
covariance, a state replaced by a new start-up) breaks the RTS recursion, whose prediction
must be exactly what the next posterior was updated from. The recorder does not need to be
told: before each propagation it checks that the state it sees is the very one it left after
the last propagation or update (same object, same nominal arrays, equal robot covariance, same
time) and otherwise closes the segment at the last consistent posterior and starts another.
A reset therefore splits the smoothing into segments; each is smoothed on its own.
"""

from __future__ import annotations

from typing import Callable, Protocol

import numpy as np

from vtolpose.estimator.core.state import FilterState
from vtolpose.estimator.smoothing.steps import Step, pack_nominal


class FilterRecorder(Protocol):
    """What the estimator calls (``Estimator.recorder``); :class:`StepRecorder` is the one in use."""

    def before_propagation(self, state: FilterState, heading_known: bool = True) -> None: ...
    def after_propagation(self, state: FilterState, F: np.ndarray) -> None: ...
    def updated(self, state: FilterState) -> None: ...
    def finish(self, state: FilterState | None, heading_known: bool = True) -> None: ...


class StepRecorder:
    """Emits steps to ``sink`` (a list's append, a chunk builder, the fixed-lag smoother)."""

    def __init__(self, sink: Callable[[Step], None]) -> None:
        self.sink = sink
        self.segment = -1
        self.steps = 0
        self._state: FilterState | None = None  # the object the current segment follows
        self._ref_t = 0
        self._ref_P: np.ndarray | None = None  # robot covariance after the last propagation or update
        self._ref_nominal: tuple = ()  # the nominal arrays then (the filter replaces them, never mutates)
        self._ref_x: np.ndarray | None = None  # their packed values, when already packed
        self._post: tuple[int, np.ndarray, np.ndarray] | None = None
        self._heading_known = True  # at the last posterior

    # ------------------------------------------------------------------------------ hooks
    def before_propagation(self, state: FilterState, heading_known: bool = True) -> None:
        """``state`` is the posterior at its time: every measurement there has been fused.
        ``heading_known``: False while the filter's yaw is arbitrary (see ``steps``)."""
        if not self._consistent(state):
            self._close()  # with the flag of the segment it closes
            self.segment += 1
            self._state = state
            state.observer = self
            n = state.robot_dim
            self._remember(state, None, state.cov[:n, :n].copy())
        self._heading_known = heading_known
        ref, x = self._ref_nominal, self._ref_x
        if x is None or state.b_g is not ref[3] or state.b_a is not ref[4]:
            x = pack_nominal(state)
        self._post = (state.t_ns, x, self._ref_P)

    def after_propagation(self, state: FilterState, F: np.ndarray) -> None:
        """The prediction at ``state.t_ns``; ``F`` the robot transition just applied (copied here)."""
        t0, x0, P0 = self._post
        n = state.robot_dim
        x_pred, P_pred = pack_nominal(state), state.cov[:n, :n].copy()
        self.sink(Step(self.segment, t0, x0, P0, state.t_ns, F.copy(), x_pred, P_pred, self._heading_known))
        self.steps += 1
        self._remember(state, x_pred, P_pred)

    def updated(self, state: FilterState) -> None:
        """A measurement was fused into ``state`` (called by the shared EKF update)."""
        if state is self._state:
            n = state.robot_dim
            self._remember(state, None, state.cov[:n, :n].copy())

    def finish(self, state: FilterState | None, heading_known: bool = True) -> None:
        """End of the data: the last posterior closes the last segment."""
        if state is not None and not self._consistent(state):
            self._close()
            self.segment += 1
            self._state = state
            n = state.robot_dim
            self._remember(state, None, state.cov[:n, :n].copy())
        self._heading_known = heading_known
        self._close()

    # --------------------------------------------------------------------------- segments
    def _remember(self, state: FilterState, x: np.ndarray | None, P: np.ndarray) -> None:
        self._ref_t, self._ref_P, self._ref_x = state.t_ns, P, x
        self._ref_nominal = (state.p, state.v, state.q, state.b_g, state.b_a)

    def _consistent(self, state: FilterState) -> bool:
        if state is not self._state or self._ref_P is None or state.t_ns != self._ref_t:
            return False
        ref = self._ref_nominal
        same = state.p is ref[0] and state.v is ref[1] and state.q is ref[2]
        if state.layout.estimates_biases:  # the thesis model's biases are no error states: it may refine them
            same = same and state.b_g is ref[3] and state.b_a is ref[4]
        n = state.robot_dim
        return same and np.array_equal(state.cov[:n, :n], self._ref_P)

    def _close(self) -> None:
        """The segment ends at the last consistent posterior (emitted once)."""
        if self._state is None or self._ref_P is None:
            return
        x = self._ref_x if self._ref_x is not None else np.concatenate(self._ref_nominal)
        self.sink(Step(self.segment, self._ref_t, x, self._ref_P, heading_known=self._heading_known))
        self.steps += 1
        if self._state.observer is self:
            self._state.observer = None
        self._state, self._ref_P, self._ref_x, self._ref_nominal = None, None, None, ()


class Recorders:
    """Several recorders on one filter (e.g. the step recorder and a reference beside it)."""

    def __init__(self, *recorders: object) -> None:
        self.recorders = recorders

    def before_propagation(self, state: FilterState, heading_known: bool = True) -> None:
        for r in self.recorders:
            r.before_propagation(state, heading_known)
        state.observer = self  # updates reach all of them

    def after_propagation(self, state: FilterState, F: np.ndarray) -> None:
        for r in self.recorders:
            r.after_propagation(state, F)

    def updated(self, state: FilterState) -> None:
        for r in self.recorders:
            r.updated(state)

    def finish(self, state: FilterState | None, heading_known: bool = True) -> None:
        for r in self.recorders:
            r.finish(state, heading_known)
