"""The exact RTS smoother with the landmarks kept: the yardstick for the robot-block approximation.

The production smoother (:mod:`.rts`) keeps only the robot block of the covariance and of the
transition. With the camera in the filter the robot is correlated with the landmarks, and the
robot alone is no longer a Markov process: a landmark re-observed later carries information
back to every pose that saw it, a path the robot-block pass does not have. This module runs
the full-state pass (mean only) so that the difference can be measured on short flights.

A propagation leaves landmarks alone (``F = diag(F_r, I)``, ``Q = diag(Q_r, 0)``), so across it
each landmark's smoothed value stays what it is and the robot's correction is ``G δ`` with the
robot rows of the full gain, ``G = (P Fᵀ)_r· (P⁻)⁻¹`` (``15 × n``), computed in the forward
pass. A new landmark's anchor is a function of the robot pose (its noise has rank 3 of 6), which
leaves the full covariance nearly singular: it is inverted at unit diagonal with a relative
jitter of 10⁻¹² (raised tenfold until the Cholesky factor exists), far below any variance. Where the map changes between two propagations
(landmarks added after a frame's update, deleted for being stale), the pass goes back over the
change: an added landmark is dropped (the smoothed values of the rest are its marginal), a
deleted one gets its smoothed value by regression on the robot and the kept landmarks in the
covariance just before the deletion (the RTS step of a selection). Cost: a Cholesky factor of
the full covariance per step, memory ``15 × n`` floats per step; for short runs only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from vtolpose.estimator.core.state import LANDMARK_DIM, FilterState
from vtolpose.estimator.smoothing.rts import apply_error, error_between
from vtolpose.estimator.smoothing.steps import pack_nominal


@dataclass(slots=True)
class _Posterior:
    t_ns: int
    x: np.ndarray  # robot nominal (16)
    ids: np.ndarray  # landmark ids, state order
    landmarks: np.ndarray  # (M, 6)


@dataclass(slots=True)
class _Prediction:
    x: np.ndarray  # robot nominal (16) after the propagation
    landmarks: np.ndarray  # (M, 6), the posterior's (a propagation leaves them alone)
    gain: np.ndarray  # (n_r, n): robot rows of the RTS gain


@dataclass(slots=True)
class _MapChange:
    """Landmarks added and deleted between a posterior (``before``) and the next one."""

    before: _Posterior
    deleted: np.ndarray  # ids
    kept: np.ndarray  # ids kept, in the order of ``regression``'s landmark columns
    regression: np.ndarray  # (6 |deleted|, n_r + 6 |kept|): deleted on robot and kept, before the change


class FullStateRecorder:
    """Records what the full-state pass needs; hook it where :class:`~.recorder.StepRecorder` goes.

    ``landmark_ids()`` gives the ids of the landmarks in state order (the camera pipeline's book).
    No resets: the flight must be one segment (check with a StepRecorder beside it). No calibration states
    (``estimator.camera.estimate_time_offset`` and ``estimate_extrinsics`` off): the pass knows the robot and the
    landmarks only.
    """

    def __init__(self, landmark_ids: Callable[[], np.ndarray]) -> None:
        self.landmark_ids = landmark_ids
        self.events: list[_Posterior | _Prediction | _MapChange] = []
        self._last: tuple[_Posterior, np.ndarray] | None = None  # the newest posterior and its full covariance
        self._P_post_r: np.ndarray | None = None  # robot columns of the posterior covariance

    def _snapshot(self, state: FilterState) -> tuple[_Posterior, np.ndarray]:
        ids = np.asarray(self.landmark_ids(), dtype=np.int64).copy()
        if len(ids) != state.n_landmarks:
            raise ValueError("landmark ids and the state's landmarks disagree")
        if state.calib.shape[0]:
            raise ValueError("the full-state pass has no calibration states (it would smooth the camera's time offset "
                             "and mounting as if they were landmarks): run without estimating them "
                             "(estimator.camera.estimate_time_offset and estimate_extrinsics off)")
        return _Posterior(state.t_ns, pack_nominal(state), ids, state.landmarks.copy()), state.cov.copy()

    def _observe(self, state: FilterState) -> tuple[_Posterior, np.ndarray]:
        """A snapshot; a map change since the last one is recorded first (against the last one)."""
        now, cov = self._snapshot(state)
        if self._last is not None and not np.array_equal(self._last[0].ids, now.ids):
            self.events.append(_map_change(*self._last, now.ids, state.robot_dim))
        self._last = (now, cov)
        return now, cov

    def before_propagation(self, state: FilterState, heading_known: bool = True) -> None:
        now, cov = self._observe(state)
        self.events.append(now)
        self._P_post_r = cov[:, : state.robot_dim]

    def after_propagation(self, state: FilterState, F: np.ndarray) -> None:
        n = state.robot_dim
        FP = self._P_post_r.copy()  # (F P)_·r: the propagation moves the robot rows only
        FP[:n] = F @ FP[:n]
        self.events.append(_Prediction(pack_nominal(state), state.landmarks.copy(), _solve_spd(state.cov, FP).T))
        self._last = self._snapshot(state)

    def updated(self, state: FilterState) -> None:
        self._observe(state)

    def finish(self, state: FilterState, heading_known: bool = True) -> None:
        self.events.append(self._observe(state)[0])

    def smooth(self) -> tuple[np.ndarray, np.ndarray]:
        """Smoothed robot nominal states (K, 16) at the posterior times (K,), in time order."""
        events = self.events
        post = events[-1]
        n = next(e for e in events if isinstance(e, _Prediction)).gain.shape[0]  # robot error dimension
        xs = post.x
        lm = {int(i): y for i, y in zip(post.ids, post.landmarks)}
        times, out = [post.t_ns], [xs]
        for k in range(len(events) - 2, -1, -1):
            event = events[k]
            if isinstance(event, _MapChange):
                lm = _before_change(event, xs, lm, n)
            elif isinstance(event, _Prediction):
                prior = events[k - 1]
                delta = np.concatenate([error_between(xs, event.x, n)]
                                       + [lm[int(i)] - y for i, y in zip(prior.ids, event.landmarks)])
                lm = {int(i): lm[int(i)] for i in prior.ids}
                xs = apply_error(prior.x, event.gain @ delta, n)
            else:
                times.append(event.t_ns)
                out.append(xs)
        return np.array(times[::-1], dtype=np.int64), np.array(out[::-1])


def _solve_spd(P: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``P⁻¹ B`` for a covariance that may be nearly singular (see the module docstring)."""
    s = 1.0 / np.sqrt(np.maximum(np.diagonal(P), 1e-300))
    A = 0.5 * (P + P.T) * s[:, None] * s[None, :]
    jitter = 1e-12
    while True:
        try:
            L = np.linalg.cholesky(A + jitter * np.eye(len(A)))
            break
        except np.linalg.LinAlgError:
            if jitter >= 1e-3:
                raise
            jitter *= 10.0
    return s[:, None] * np.linalg.solve(L.T, np.linalg.solve(L, s[:, None] * B))


def _map_change(before: _Posterior, cov: np.ndarray, ids_after: np.ndarray, n: int) -> _MapChange:
    deleted_mask = ~np.isin(before.ids, ids_after)
    kept_idx, deleted_idx = np.flatnonzero(~deleted_mask), np.flatnonzero(deleted_mask)

    def cols(idx: np.ndarray) -> np.ndarray:
        return (n + LANDMARK_DIM * idx[:, None] + np.arange(LANDMARK_DIM)).reshape(-1)

    given = np.concatenate([np.arange(n), cols(kept_idx)])
    target = cols(deleted_idx)
    regression = _solve_spd(cov[np.ix_(given, given)], cov[np.ix_(given, target)]).T if len(target) else \
        np.zeros((0, len(given)))
    return _MapChange(before, before.ids[deleted_idx], before.ids[kept_idx], regression)


def _before_change(change: _MapChange, xs: np.ndarray, lm: dict[int, np.ndarray], n: int) -> dict[int, np.ndarray]:
    """Smoothed landmarks before a map change: the added ones dropped, the deleted ones regressed."""
    before = change.before
    index = {int(i): k for k, i in enumerate(before.ids)}
    out = {int(i): lm[int(i)] for i in change.kept}
    if len(change.deleted):
        given = np.concatenate([error_between(xs, before.x, n)]
                               + [lm[int(i)] - before.landmarks[index[int(i)]] for i in change.kept])
        moved = (change.regression @ given).reshape(-1, LANDMARK_DIM)
        for i, d in zip(change.deleted, moved):
            out[int(i)] = before.landmarks[index[int(i)]] + d
    return out
