"""A recorded stream whose clock steps, put back on the other streams' time.

A device clock that resets, a counter that wraps unexpectedly, two recordings spliced into one
file: from one row on, every stamp is off by the same amount, forward or back. Dropping what is
out of order would lose everything up to the old time (thousands of IMU rows for a 5 s step back)
and leave the stream seconds away from the GPS and camera; keeping a forward step would leave a
hole longer than the flight. Neither is a loss of data: the rows are there, only their stamps lie.

A step is a jump between two rows that the stream's own rate cannot explain, followed by a run
of rows at that rate (``min_run``; a single wrong stamp is damage for the order check, not a step):

- back by more than ``back_tolerance_s``: time cannot go back, so it is a step;
- forward by more than ``forward_gap_s``: a step if the stream then runs past the other streams'
  end by more than half the jump (the rows continued; a real gap of lost samples would end with
  the others), a gap otherwise. Without other streams to compare with, a forward jump stays a gap.

A step is undone by re-anchoring the run that follows it: its first row one sample period after
the last row before the step, the rows after it shifted by the same amount. Pure computation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NS = 1_000_000_000


@dataclass(frozen=True, slots=True)
class ClockStep:
    """One step undone: at row ``row`` (in file order) the stamps jumped by ``jump_ns``; shifted by ``shift_ns``."""

    row: int
    t_ns: int  # the stamp of that row as recorded
    jump_ns: int  # its stamp less the previous row's
    shift_ns: int  # added to it and every row after it

    def describe(self) -> str:
        direction = "back" if self.jump_ns < 0 else "forward"
        return (f"the clock steps {direction} by {abs(self.jump_ns) / NS:.6g} s at data row {self.row + 1} "
                f"(t_ns={self.t_ns}): rows from there re-anchored by {self.shift_ns / NS:+.6g} s")


@dataclass(frozen=True, slots=True)
class StepOptions:
    back_tolerance_s: float = 0.1  # smaller steps back are out-of-order rows (the order check drops them)
    forward_gap_s: float = 1.0  # smaller jumps forward are gaps (the estimator bridges or resets over them)
    min_run: int = 20  # rows at the stream's rate that must follow a jump for it to be a step


def sample_period_ns(t_ns: np.ndarray) -> int:
    """The stream's typical spacing (median of its positive steps), 1 ns if it has none."""
    d = np.diff(np.asarray(t_ns, dtype=np.int64))
    d = d[d > 0]
    return int(np.median(d)) if d.size else 1


def reanchor(t_ns: np.ndarray, reference_end_ns: int | None, options: StepOptions = StepOptions()
             ) -> tuple[np.ndarray, list[ClockStep]]:
    """``t_ns`` (file order) with its clock steps undone, and the steps. ``reference_end_ns``: the last stamp
    of the other streams (None: there are none)."""
    t = np.asarray(t_ns, dtype=np.int64)
    if t.size < 2:
        return t, []
    period = sample_period_ns(t)
    d = np.diff(t)
    back_ns, gap_ns = int(options.back_tolerance_s * NS), int(options.forward_gap_s * NS)
    jumps = np.flatnonzero((d < -back_ns) | (d > max(gap_ns, 0)))
    if jumps.size == 0:
        return t, []
    out = t.copy()
    steps: list[ClockStep] = []
    starts = [0, *(jumps + 1).tolist()]
    ends = [*starts[1:], t.size]
    anchor = ends[0] - 1  # the last row of the runs kept so far
    for row, end in zip(starts[1:], ends[1:]):
        if end - row < options.min_run:
            continue  # a few rows off: damage for the order check, and no anchor for what follows
        before = int(out[anchor])
        anchor = end - 1
        jump = int(out[row]) - before
        if -back_ns <= jump <= gap_ns:
            continue  # back in line with the rows before a few bad ones
        if jump > 0:
            overhang = int(out[-1]) - reference_end_ns if reference_end_ns is not None else None
            if overhang is None or overhang <= jump // 2:
                continue  # a real gap: the stream ends with the others
        shift = before + period - int(out[row])
        out[row:] += shift
        steps.append(ClockStep(row, int(t[row]), jump, shift))
    return out, steps
