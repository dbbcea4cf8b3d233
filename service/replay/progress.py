"""A one-line progress display for long replays; silent when stderr is not a terminal."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    def __init__(self, total: float, label: str, unit: str = "s", stream: TextIO | None = None, enabled: bool | None = None) -> None:
        self.total = max(float(total), 1e-9)
        self.label = label
        self.unit = unit
        self.stream = stream or sys.stderr
        self.enabled = self.stream.isatty() if enabled is None else enabled
        self._start = time.perf_counter()
        self._last_draw = 0.0

    def update(self, done: float, note: str = "") -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        if now - self._last_draw < 0.1 and done < self.total:
            return
        self._last_draw = now
        frac = min(max(done / self.total, 0.0), 1.0)
        elapsed = now - self._start
        eta = elapsed * (1.0 - frac) / frac if frac > 0 else float("nan")
        bar = "#" * int(frac * 30)
        rate = f"{done / elapsed:.0f}{self.unit}/s" if elapsed > 0 else ""
        self.stream.write(
            f"\r{self.label} [{bar:<30}] {100 * frac:5.1f}%  {done:.1f}/{self.total:.1f} {self.unit}  {rate}  eta {eta:4.0f} s {note}\033[K"
        )
        self.stream.flush()

    def finish(self, note: str = "") -> None:
        if not self.enabled:
            return
        self._last_draw = 0.0
        self.update(self.total, note)
        self.stream.write("\n")
        self.stream.flush()
