"""Fixed-lag smoothing for the live daemon: the RTS pass over the last seconds, in bounded slices.

Steps come in from the recorder as the filter runs. A *sweep* starts at the newest posterior
(time ``T``) and runs the RTS recursion backwards; the estimates it reaches at or before
``T − lag`` are final for the mapper (each has had at least ``lag`` seconds of later
measurements) and are handed out when the sweep reaches the last estimate handed out before.
Then the next sweep starts from the newest posterior again. Each call to :meth:`work` does at
most ``steps_per_call`` backward steps, so the work per IMU sample is bounded and can sit after
the pose has left; with ``s`` steps per call a sweep spans about ``lag·s/(s−1)`` of filter
time, and the smoothed estimates arrive between ``lag`` and about ``lag·s/(s−1)`` late.

Memory is bounded by ``max_window_s`` of steps: if the smoother falls that far behind (it is
starved of calls), the oldest steps are dropped unsmoothed and counted; their times keep the
filtered estimate.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

import numpy as np

from vtolpose.estimator.smoothing import rts_kernel
from vtolpose.estimator.smoothing.rts import POSE_IX, error_between, published_pose_cov, stacked_gains
from vtolpose.estimator.smoothing.steps import Step

_POSE_BLOCK = np.ix_(POSE_IX, POSE_IX)
GAIN_BATCH = 8  # gains computed together when a sweep meets steps without one (bounds a call's work)


@dataclass(frozen=True, slots=True)
class SmoothedPose:
    """A smoothed estimate: nominal ``[p, v, q, b_g, b_a]``, pose covariance over [δp, δθ], velocity variances."""

    t_ns: int
    x: np.ndarray
    pose_cov: np.ndarray  # as published: an unknown heading has the variance of one anywhere on the circle
    vel_var: np.ndarray
    heading_known: bool = True

    @property
    def p(self) -> np.ndarray:
        return self.x[0:3]

    @property
    def v(self) -> np.ndarray:
        return self.x[3:6]

    @property
    def q(self) -> np.ndarray:
        return self.x[6:10]


@dataclass(slots=True)
class _Sweep:
    index: int  # the next step to smooth (absolute index: counts dropped steps too)
    threshold_ns: int  # estimates at or before this time are handed out
    e: np.ndarray | None = None  # smoothed correction of the last step reached (rts: e_k)
    Ps: np.ndarray | None = None
    segment: int = -1
    last_t: int | None = None  # the oldest time reached (dedups a segment end against the next start)
    reached: list = field(default_factory=list)  # the final estimates so far, newest first


class FixedLagSmoother:
    """Feed it the recorder's steps (:meth:`add`), call :meth:`work` after each IMU sample; see the module docstring."""

    def __init__(self, lag_s: float, steps_per_call: int = 4, max_window_s: float = 10.0) -> None:
        if not lag_s > 0.0:
            raise ValueError(f"fixed lag must be positive, got {lag_s}")
        if steps_per_call < 2:
            raise ValueError(f"steps_per_call must be at least 2 (a sweep must outrun the filter), got {steps_per_call}")
        if max_window_s <= lag_s:
            raise ValueError(f"max_window_s ({max_window_s}) must exceed the lag ({lag_s})")
        self.lag_ns = int(round(lag_s * 1e9))
        self.steps_per_call = steps_per_call
        self.max_window_ns = int(round(max_window_s * 1e9))
        self._steps: list[Step] = []
        self._times: list[int] = []
        self._gains: list[tuple[np.ndarray, np.ndarray, np.ndarray] | None] = []
        self._base = 0  # absolute index of self._steps[0]
        self._sweep: _Sweep | None = None
        self.emitted_t_ns: int | None = None  # the newest time handed out
        self.emitted = 0
        self.dropped = 0  # steps that left the window before a sweep reached them

    # ------------------------------------------------------------------------------ input
    def add(self, step: Step) -> None:
        """A recorded step (the recorder's sink)."""
        self._steps.append(step)
        self._times.append(step.t_ns)
        self._gains.append(None)
        oldest_kept = step.t_ns - self.max_window_ns
        drop = bisect.bisect_left(self._times, oldest_kept)
        if drop:
            lost = [t for t in self._times[:drop] if self.emitted_t_ns is None or t > self.emitted_t_ns]
            if lost:
                self.dropped += len(lost)
                self.emitted_t_ns = max(lost)  # those times keep their filtered estimate
            self._forget(drop)
            self._sweep = None  # its window moved under it: start again from the newest

    def _forget(self, k: int) -> None:
        del self._steps[:k], self._times[:k], self._gains[:k]
        self._base += k

    @property
    def held_steps(self) -> int:
        return len(self._steps)

    # ------------------------------------------------------------------------------- work
    def work(self, budget: int | None = None) -> list[SmoothedPose]:
        """At most ``budget`` (default ``steps_per_call``) backward steps; the estimates that became final."""
        budget = self.steps_per_call if budget is None else budget
        out: list[SmoothedPose] = []
        while budget > 0:
            if self._sweep is None and not self._start(None):
                break
            done, used, poses = self._run(self._sweep, budget)
            budget -= used
            if done:
                out += poses
                self._sweep = None
            if not used:
                break
        return out

    def flush(self) -> list[SmoothedPose]:
        """End of the data: everything not yet handed out, smoothed with whatever came after it."""
        out: list[SmoothedPose] = []
        self._sweep = None
        if self._start(np.iinfo(np.int64).max):
            _, _, out = self._run(self._sweep, len(self._steps) + 1)
            self._sweep = None
        return out

    def _start(self, threshold: int | None) -> bool:
        """A new sweep from the newest step, if some step between the last hand-out and ``T − lag`` waits."""
        if not self._steps:
            return False
        if threshold is None:
            threshold = self._times[-1] - self.lag_ns
        first_waiting = 0 if self.emitted_t_ns is None else bisect.bisect_right(self._times, self.emitted_t_ns)
        if first_waiting >= len(self._times) or self._times[first_waiting] > threshold:
            return False
        self._sweep = _Sweep(self._base + len(self._steps) - 1, threshold)
        return True

    def _run(self, sweep: _Sweep, budget: int) -> tuple[bool, int, list[SmoothedPose]]:
        """Advance ``sweep`` by up to ``budget`` steps. Done: the estimates it makes final, in time order."""
        used = 0
        stop_t = self.emitted_t_ns
        while used < budget:
            i = sweep.index - self._base
            step = self._steps[i]
            if stop_t is not None and step.t_ns <= stop_t:
                return self._finish(sweep, used)
            if step.ends_segment or sweep.e is None or sweep.segment != step.segment:
                sweep.e, sweep.Ps = np.zeros(step.P.shape[0]), step.P  # the newest posterior, or a segment's last
            else:
                C, D, u = self._gain(i)
                sweep.e, sweep.Ps = rts_kernel.backward_step(C, D, u, sweep.e, sweep.Ps)  # compiled, bit for bit
            sweep.segment = step.segment
            used += 1
            if step.t_ns <= sweep.threshold_ns and (sweep.last_t is None or step.t_ns < sweep.last_t):
                sweep.last_t = step.t_ns
                Ps = sweep.Ps
                sweep.reached.append(SmoothedPose(step.t_ns, rts_kernel.apply_error(step.x, sweep.e, Ps.shape[0]),
                                                  published_pose_cov(Ps[_POSE_BLOCK], step.heading_known),
                                                  np.diagonal(Ps)[3:6].copy(), step.heading_known))
            sweep.index -= 1
            if sweep.index < self._base:
                return self._finish(sweep, used)
        return False, used, []

    def _finish(self, sweep: _Sweep, used: int) -> tuple[bool, int, list[SmoothedPose]]:
        poses = sweep.reached[::-1]
        if not poses:
            return True, used, []
        self.emitted_t_ns = poses[-1].t_ns
        self.emitted += len(poses)
        keep = bisect.bisect_left(self._times, self.emitted_t_ns)
        if keep:
            self._forget(keep)
        return True, used, poses

    def _gain(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``C, D`` and the correction ``u`` at the successor (``rts``), computed once per step: in a batch with
        the next few older steps that have none yet (the sweep needs them next), so a call stays short."""
        cached = self._gains[i]
        if cached is None:
            todo = [i]
            for j in range(i - 1, max(i - GAIN_BATCH, -1), -1):
                if self._gains[j] is not None:
                    break
                if not self._steps[j].ends_segment:
                    todo.append(j)
            steps, successors = [self._steps[j] for j in todo], [self._steps[j + 1] for j in todo]
            P, F, P_pred = (np.array([getattr(s, name) for s in steps]) for name in ("P", "F", "P_pred"))
            C, D = stacked_gains(P, F, P_pred, np.ones(len(steps), dtype=bool))  # as the backward pass
            u = error_between(np.array([s.x for s in successors]), np.array([s.x_pred for s in steps]), steps[0].P.shape[0])
            for k, j in enumerate(todo):
                self._gains[j] = (C[k], D[k], u[k])
            cached = self._gains[i]
        return cached
