"""Who sees the filter's steps, decided before the estimator is built: it is given its recorder at construction.

A :class:`SmoothingPlan` says what the steps are for: a fixed-lag smoother keeping the history smoothed
(``lag_s`` > 0: mappers read it), a replay's step files for the backward pass, another recorder beside them
(a benchmark's full-state one). :class:`StepTaps` makes the one recorder the estimator gets: each step goes to
every sink, and a sink that fails is dropped and reported, never costing the filter its step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from vtolpose.estimator import FilterRecorder, FixedLagSmoother, Recorders, Step, StepRecorder


@dataclass(frozen=True, slots=True)
class SmoothingPlan:
    lag_s: float = 0.0  # > 0: a fixed-lag smoother keeps the history smoothed after this lag
    steps_per_sample: int = 4
    max_window_s: float = 10.0
    step_sink: Callable[[Step], None] | None = None  # sees every step too (a replay's backward pass)
    beside: FilterRecorder | None = None  # another recorder, given every propagation and update as well

    @property
    def records(self) -> bool:
        return self.lag_s > 0.0 or self.step_sink is not None or self.beside is not None


class StepTaps:
    """The recorder for the estimator's constructor, and the fixed-lag smoother it feeds (if any)."""

    def __init__(self, plan: SmoothingPlan) -> None:
        self.smoother = FixedLagSmoother(plan.lag_s, plan.steps_per_sample, plan.max_window_s) if plan.lag_s > 0.0 else None
        self._sinks = [s for s in (self.smoother.add if self.smoother else None, plan.step_sink) if s is not None]
        self._on_failure: Callable[[str, BaseException], None] = lambda what, exc: None
        self.steps = StepRecorder(self._fan_out) if self._sinks else None
        recorders = [r for r in (self.steps, plan.beside) if r is not None]
        self.recorder: FilterRecorder | None = recorders[0] if len(recorders) == 1 else Recorders(*recorders) if recorders else None

    def report_failures_to(self, on_failure: Callable[[str, BaseException], None]) -> None:
        self._on_failure = on_failure

    def _fan_out(self, step: Step) -> None:
        for sink in list(self._sinks):
            try:
                sink(step)
            except Exception as exc:  # a smoother's failure must never cost the filter its step
                self._on_failure("smoothing step sink (stopped)", exc)
                self._sinks.remove(sink)
