"""One benchmark figure: its value, unit, note and, where it has one, its target and verdict.

A target is written as the comparison the value must pass, e.g. ``">= 300"`` (a real-time
factor) or ``"<= 25"`` (milliseconds per frame). Absolute figures hold for the machine they were
measured on only; ``vtolpose bench`` prints that machine first.
"""

from __future__ import annotations

import math
import operator
from typing import NamedTuple

_OPS = {">=": operator.ge, "<=": operator.le, ">": operator.gt, "<": operator.lt}


class Row(NamedTuple):
    name: str
    value: float
    unit: str
    note: str = ""
    target: str | None = None  # e.g. ">= 300"; None: a figure to read, with no target

    @property
    def verdict(self) -> str:
        """``pass``, ``short`` (missed the target) or ``-`` (no target)."""
        if self.target is None:
            return "-"
        op, _, bound = self.target.partition(" ")
        if op not in _OPS:
            raise ValueError(f"benchmark target {self.target!r}: expected '<op> <number>' with op one of {list(_OPS)}")
        if not math.isfinite(self.value):
            return "short"
        return "pass" if _OPS[op](self.value, float(bound)) else "short"

    def line(self) -> str:
        target = f"target {self.target:<8} {self.verdict:<5}" if self.target else f"{'':<21}"
        return f"  {self.name:<50} {self.value:>10.4g} {self.unit:<12} {target} {self.note}".rstrip()
