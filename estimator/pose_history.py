"""A bounded, time-indexed pose history with interpolation: what ``pose/at`` and ``trajectory`` answer from.

The history holds the best estimate the service has for each time. Entries come in three
kinds (:data:`KINDS`): *smoothed* poses (the fixed-lag smoother's, which also used the
measurements up to a lag after their time), *filtered* poses (the delayed filter's states,
final once the fusion horizon has passed them) and *predicted* poses (IMU-propagated ahead of
the horizon, newer than every fused pose). A better kind replaces the worse entries over the
span it covers, so the mapper never sees a prediction where a filtered estimate exists, nor a
filtered one where a smoothed one does. Entries older than ``span_s`` before the newest are
dropped, so memory is bounded by ``span_s`` times the pose rate.

Interpolation is linear in position, velocity, angular rate and covariance (a convex blend of
two covariances stays positive semi-definite) and spherical (slerp) in attitude; a pose
interpolated between two kinds is of the worse. Times outside the history raise
:class:`OutsideHistory`; nothing is extrapolated.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vtolpose.estimator.core.columns import make_room
from vtolpose.estimator.core.rotation import quat_slerp

# One row per pose: p (3), q (4, w first), v (3), w (3, body rate), cov (36, [δp, δθ] row-major).
P, Q, V, W, COV = slice(0, 3), slice(3, 7), slice(7, 10), slice(10, 13), slice(13, 49)
ROW = 49
KINDS = ("predicted", "filtered", "smoothed")  # worst to best; stored as their index
PREDICTED, FILTERED, SMOOTHED = 0, 1, 2


class OutsideHistory(LookupError):
    """The requested time is not covered by the history (too old, in the future, or empty)."""


@dataclass(frozen=True, slots=True)
class PoseSample:
    """One pose: world NED position/velocity, body→world attitude (w first), body rate, 6×6 covariance."""

    t_ns: int
    p: np.ndarray
    q: np.ndarray
    v: np.ndarray
    w: np.ndarray
    cov: np.ndarray
    fused: bool
    kind: str = "filtered"  # predicted | filtered | smoothed (KINDS)


@dataclass(frozen=True, slots=True)
class PoseWindow:
    """Poses as columns (N rows, time-ordered): what ``trajectory`` returns."""

    t_ns: np.ndarray
    p: np.ndarray
    q: np.ndarray
    v: np.ndarray
    w: np.ndarray
    fused: np.ndarray
    kind: np.ndarray | None = None  # per pose: predicted | filtered | smoothed (None from an older service)
    cov: np.ndarray | None = None  # (N, 6, 6) over [δp, δθ] per pose (None from an older service)

    def __len__(self) -> int:
        return int(self.t_ns.size)

    def interpolate(self, t_ns: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """Positions (N×3) and attitudes (N×4) at ``t_ns`` (each within the window, else OutsideHistory)."""
        rows = np.concatenate([self.p, self.q], axis=1)
        out = interpolate_rows(self.t_ns, rows, np.atleast_1d(np.asarray(t_ns, dtype=np.int64)), q_cols=slice(3, 7))
        return out[:, 0:3], out[:, 3:7]


def interpolate_rows(times: np.ndarray, rows: np.ndarray, t_query: np.ndarray, q_cols: slice = Q) -> np.ndarray:
    """Rows at ``t_query`` from time-sorted ``rows``: linear blend, slerp on the quaternion columns.

    Every query time must lie within ``[times[0], times[-1]]``; an exact time returns its row.
    """
    t_query = np.asarray(t_query, dtype=np.int64)
    if times.size == 0:
        raise OutsideHistory("the history is empty")
    lo_t, hi_t = int(times[0]), int(times[-1])
    outside = (t_query < lo_t) | (t_query > hi_t)
    if np.any(outside):
        bad = int(t_query[np.argmax(outside)])
        raise OutsideHistory(f"t_ns={bad} is outside the history [{lo_t}, {hi_t}]")
    right = np.clip(np.searchsorted(times, t_query, side="left"), 0, times.size - 1)
    left = np.maximum(right - 1, 0)
    exact = times[right] == t_query
    left = np.where(exact, right, left)
    span = (times[right] - times[left]).astype(np.float64)
    alpha = np.where(span > 0, (t_query - times[left]) / np.where(span > 0, span, 1.0), 0.0)
    a, b = rows[left], rows[right]
    out = a + alpha[:, None] * (b - a)
    out[:, q_cols] = quat_slerp(a[:, q_cols], b[:, q_cols], alpha)
    return out


class PoseHistory:
    """Fused poses in a compacting array, predicted poses in a short tail after them."""

    def __init__(self, span_s: float, initial_capacity: int = 4096) -> None:
        if span_s <= 0:
            raise ValueError(f"history span must be positive, got {span_s}")
        self.span_ns = int(span_s * 1e9)
        self._t = np.zeros(initial_capacity, dtype=np.int64)
        self._rows = np.zeros((initial_capacity, ROW))
        self._kind = np.zeros(initial_capacity, dtype=np.int8)  # FILTERED or SMOOTHED
        self._start = 0
        self._end = 0
        self._tail_t: list[int] = []
        self._tail_rows: list[np.ndarray] = []

    # ------------------------------------------------------------------------- adding
    @staticmethod
    def make_row(p: np.ndarray, q: np.ndarray, v: np.ndarray, w: np.ndarray, cov: np.ndarray) -> np.ndarray:
        return np.concatenate([p, q, v, w, np.asarray(cov).reshape(36)])

    def add_fused(self, t_ns: int, row: np.ndarray) -> None:
        """A final estimate; times must increase. Drops the predictions it supersedes."""
        if self._end > self._start and t_ns <= self._t[self._end - 1]:
            return
        while self._tail_t and self._tail_t[0] <= t_ns:
            self._tail_t.pop(0)
            self._tail_rows.pop(0)
        if self._end == self._t.size:
            self._make_room(1)
        self._t[self._end] = t_ns
        self._rows[self._end] = row
        self._kind[self._end] = FILTERED
        self._end += 1
        self._evict(max(t_ns, self._tail_t[-1] if self._tail_t else t_ns))

    def add_smoothed(self, t_ns: np.ndarray, rows: np.ndarray) -> int:
        """Smoothed estimates (increasing times) replace the held entries over their span.

        The filtered entries from the first to the last given time go; those before stay (a
        smoother that started late, or skipped a stretch). Each row's body rate is taken from
        the entries it replaces (the smoother does not estimate it). Returns how many were added.
        """
        t_ns = np.asarray(t_ns, dtype=np.int64)
        rows = np.array(rows, dtype=float).reshape(-1, ROW)
        main_t = self._t[self._start : self._end]
        if main_t.size == 0 or t_ns.size == 0:
            return 0
        smoothed = self._kind[self._start : self._end] == SMOOTHED
        newest_smoothed = int(main_t[smoothed][-1]) if np.any(smoothed) else None
        keep = (t_ns >= main_t[0]) if newest_smoothed is None else (t_ns > newest_smoothed)
        t_ns, rows = t_ns[keep], rows[keep]
        if t_ns.size == 0:
            return 0
        base = main_t[0]
        rel = (main_t - base).astype(np.float64)
        for c in range(W.start, W.stop):
            rows[:, c] = np.interp((t_ns - base).astype(np.float64), rel, self._rows[self._start : self._end, c])
        i0 = self._start + int(np.searchsorted(main_t, t_ns[0], side="left"))
        j = self._start + int(np.searchsorted(main_t, t_ns[-1], side="right"))
        m, after = t_ns.size, self._end - j
        need = (i0 - self._start) + m + after  # live entries once replaced
        if self._start + need > self._t.size:
            shift = self._start  # _make_room moves the live part to index 0
            self._make_room(need - (self._end - self._start))
            i0, j = i0 - shift, j - shift
        for array in (self._t, self._rows, self._kind):
            array[i0 + m : i0 + m + after] = array[j : j + after].copy()
        self._t[i0 : i0 + m], self._rows[i0 : i0 + m], self._kind[i0 : i0 + m] = t_ns, rows, SMOOTHED
        self._end = i0 + m + after
        while self._tail_t and self._tail_t[0] <= int(t_ns[-1]):
            self._tail_t.pop(0)
            self._tail_rows.pop(0)
        self._evict(self.bounds()[1])
        return int(m)

    def add_predicted(self, t_ns: int, row: np.ndarray) -> None:
        """A prediction newer than every fused pose and every earlier prediction (else ignored)."""
        if self._end > self._start and t_ns <= self._t[self._end - 1]:
            return
        if self._tail_t and t_ns <= self._tail_t[-1]:
            return
        self._tail_t.append(t_ns)
        self._tail_rows.append(row)
        self._evict(t_ns)

    def _make_room(self, extra: int) -> None:
        """Room for ``extra`` more entries after the live ones, which start at index 0 afterwards."""
        (self._t, self._rows, self._kind), self._start, self._end = make_room(
            (self._t, self._rows, self._kind), self._start, self._end, extra)

    def _evict(self, newest: int) -> None:
        oldest_kept = newest - self.span_ns
        if self._end > self._start and self._t[self._start] < oldest_kept:
            self._start += int(np.searchsorted(self._t[self._start : self._end], oldest_kept, side="left"))

    # ------------------------------------------------------------------------- queries
    def __len__(self) -> int:
        return self._end - self._start + len(self._tail_t)

    @property
    def capacity(self) -> int:
        return int(self._t.size)

    def bounds(self) -> tuple[int, int] | None:
        """(oldest, newest) time held, or None when empty."""
        if not len(self):
            return None
        first = int(self._t[self._start]) if self._end > self._start else self._tail_t[0]
        last = self._tail_t[-1] if self._tail_t else int(self._t[self._end - 1])
        return first, last

    def _columns(self, t0_ns: int, t1_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Times, rows and kinds of the entries in [t0, t1] plus one neighbour each side."""
        t_main = self._t[self._start : self._end]
        lo = max(int(np.searchsorted(t_main, t0_ns, side="left")) - 1, 0)
        hi = min(int(np.searchsorted(t_main, t1_ns, side="right")) + 1, t_main.size)
        times, rows = t_main[lo:hi], self._rows[self._start + lo : self._start + hi]
        kind = self._kind[self._start + lo : self._start + hi]
        if self._tail_t and t1_ns >= (int(t_main[-1]) if t_main.size else self._tail_t[0]):
            times = np.concatenate([times, np.asarray(self._tail_t, dtype=np.int64)])
            rows = np.concatenate([rows, np.asarray(self._tail_rows).reshape(-1, ROW)])
            kind = np.concatenate([kind, np.full(len(self._tail_t), PREDICTED, dtype=np.int8)])
        return times, rows, kind

    def at(self, t_ns: int) -> PoseSample:
        """The pose at ``t_ns``, interpolated between the two entries around it."""
        bounds = self.bounds()
        if bounds is None:
            raise OutsideHistory("the history is empty")
        if not bounds[0] <= t_ns <= bounds[1]:
            raise OutsideHistory(f"t_ns={t_ns} is outside the history [{bounds[0]}, {bounds[1]}]")
        times, rows, kinds = self._columns(t_ns, t_ns)
        row = interpolate_rows(times, rows, np.array([t_ns], dtype=np.int64))[0]
        k = int(np.searchsorted(times, t_ns, side="left"))
        kind = int(kinds[k]) if times[k] == t_ns else int(min(kinds[k - 1], kinds[k]))
        return PoseSample(int(t_ns), row[P], row[Q], row[V], row[W], row[COV].reshape(6, 6), kind != PREDICTED, KINDS[kind])

    def window(self, t0_ns: int, t1_ns: int) -> PoseWindow:
        """Every entry in ``[t0, t1]``, plus the last one before ``t0`` and the first after ``t1`` when
        the window's ends fall between entries, so that any time in ``[t0, t1]`` the history covers
        can be interpolated from the window alone. OutsideHistory when it does not overlap the history."""
        bounds = self.bounds()
        if t1_ns < t0_ns:
            raise ValueError(f"window end {t1_ns} is before its start {t0_ns}")
        if bounds is None or t1_ns < bounds[0] or t0_ns > bounds[1]:
            span = "empty" if bounds is None else f"[{bounds[0]}, {bounds[1]}]"
            raise OutsideHistory(f"window [{t0_ns}, {t1_ns}] does not overlap the history {span}")
        times, rows, kinds = self._columns(t0_ns, t1_ns)
        lo = max(int(np.searchsorted(times, t0_ns, side="right")) - 1, 0)  # the last entry at or before t0
        hi = min(int(np.searchsorted(times, t1_ns, side="left")) + 1, times.size)  # the first at or after t1
        times, rows, kinds = times[lo:hi], rows[lo:hi], kinds[lo:hi]
        return PoseWindow(times.copy(), rows[:, P].copy(), rows[:, Q].copy(), rows[:, V].copy(), rows[:, W].copy(),
                          kinds != PREDICTED, np.asarray(KINDS)[kinds], rows[:, COV].reshape(-1, 6, 6).copy())
