"""Arrays that hold a window of rows (sharing their first axis) and make room for more in place: the
pose history, the start's sample window and a replay's trajectory keep their rows this way."""

from __future__ import annotations

import numpy as np


def make_room(columns: tuple[np.ndarray, ...], start: int, end: int,
              extra: int) -> tuple[tuple[np.ndarray, ...], int, int]:
    """Room for ``extra`` more rows after the live ones, ``[start, end)`` of each of ``columns``: the live rows
    slid to the front of the same arrays where they and the extra fill at most half of them, else copied into
    arrays twice as long (or as long as needed). Either way the next call is at least as many rows away as are
    copied now (amortised O(1) per row, also for a sliding window that stays nearly as long as its arrays).
    Returns the columns, then 0 and the number of live rows (where the live rows now start and end)."""
    n = end - start
    size = len(columns[0])
    if n + extra <= size // 2:
        for column in columns:
            column[:n] = column[start:end]
        return columns, 0, n
    size = max(2 * size, n + extra)
    grown = tuple(np.zeros((size, *column.shape[1:]), column.dtype) for column in columns)
    for new, old in zip(grown, columns):
        new[:n] = old[start:end]
    return grown, 0, n
