"""Figures written for people: rounded numbers and plain words, never a Python repr or float noise."""

from __future__ import annotations

import math
from typing import Any


def number(value: float, digits: int = 4) -> str:
    """``digits`` significant figures, integers as integers: 58.080000000000005 → 58.08."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if not math.isfinite(value):
        return str(value)
    return f"{value:.{digits}g}"


def describe(value: Any) -> str:
    """A nested mapping as one line: ``{'gps': {'chi2_gate': 28}}`` → ``gps: chi2_gate 28``."""
    if isinstance(value, dict):
        parts = []
        for key, item in value.items():
            sep = ": " if isinstance(item, dict) else " "
            parts.append(f"{key}{sep}{describe(item)}")
        nested = any(isinstance(v, dict) for v in value.values())
        return ("; " if nested else ", ").join(parts) or "none"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(describe(v) for v in value) + "]"
    if isinstance(value, (int, float)):
        return number(value)
    return "n/a" if value is None else str(value)


def field_lines(doc: dict[str, Any], indent: str = "  ") -> list[str]:
    """One ``key: value`` line per top-level key, values through :func:`describe`."""
    return [f"{indent}{key.replace('_', ' ')}: {describe(value)}" for key, value in doc.items()]
