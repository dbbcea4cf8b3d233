"""A one-line progress display for long replays; silent when stderr is not a terminal.

It draws as soon as it exists (so a replay that spends seconds reading its dataset is not a
blank screen), then at most ten times a second. The ETA is shown once it means something: after
half a second of wall time and 1 % of the work, from the average rate so far.
"""

from __future__ import annotations

import math
import sys
import time
from typing import TextIO

MIN_ETA_WALL_S = 0.5
MIN_ETA_FRACTION = 0.01


def _duration(seconds: float) -> str:
    seconds = max(0.0, seconds)
    if seconds < 60:
        return f"{seconds:.0f} s"
    minutes, sec = divmod(int(round(seconds)), 60)
    if minutes < 60:
        return f"{minutes} min {sec:02d} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min"


class Progress:
    def __init__(self, total: float | None, label: str, unit: str = "s", stream: TextIO | None = None,
                 enabled: bool | None = None, clock=time.perf_counter) -> None:
        self.total = None if total is None else max(float(total), 1e-9)  # None: not known yet
        self.label = label
        self.unit = unit
        self.stream = stream or sys.stderr
        self.enabled = self.stream.isatty() if enabled is None else enabled
        self._clock = clock
        self._start = clock()
        self._last_draw = -math.inf
        self._drawn_with_total = False
        self.done = 0.0
        if self.enabled:
            self._draw(0.0, "reading the data")

    def line(self, done: float, note: str = "") -> str:
        """The text drawn for ``done`` units of ``total`` (no terminal control characters)."""
        if self.total is None:
            return f"{self.label}  {note}".rstrip()
        frac = min(max(done / self.total, 0.0), 1.0)
        elapsed = self._clock() - self._start
        bar = "#" * int(frac * 30)
        parts = [f"{self.label} [{bar:<30}] {100 * frac:5.1f}%", f"{done:.1f}/{self.total:.1f} {self.unit}"]
        if elapsed > 0 and done > 0:
            parts.append(f"{done / elapsed:.1f} {self.unit}/s")
        if frac >= 1.0:
            parts.append(f"done in {_duration(elapsed)}")
        elif elapsed >= MIN_ETA_WALL_S and frac >= MIN_ETA_FRACTION:
            parts.append(f"eta {_duration(elapsed * (1.0 - frac) / frac)}")
        else:
            parts.append("eta --")
        if note:
            parts.append(note)
        return "  ".join(parts)

    def _draw(self, done: float, note: str = "") -> None:
        self._last_draw = self._clock()
        self._drawn_with_total = self.total is not None
        self.stream.write("\r" + self.line(done, note) + "\033[K")
        self.stream.flush()

    def update(self, done: float, note: str = "") -> None:
        self.done = done
        if not self.enabled:
            return
        # At most ten draws a second, but the first one that knows the total (0 %) and the last always.
        if (self._clock() - self._last_draw < 0.1 and (self.total is None or done < self.total)
                and self._drawn_with_total == (self.total is not None)):
            return
        self._draw(done, note)

    def finish(self, note: str = "") -> None:
        if not self.enabled:
            return
        self._draw(self.total if self.total is not None else self.done, note)
        self.stream.write("\n")
        self.stream.flush()
