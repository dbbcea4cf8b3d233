"""Cutting a stream of samples into pieces of given lengths, as a replay hands runs of them over."""

from __future__ import annotations

from typing import Iterable, Iterator


def pieces(n: int, lengths: Iterable[int]) -> Iterator[tuple[int, int]]:
    """(start, stop) of consecutive pieces of ``n`` samples with ``lengths`` (the last cut at ``n``; the rest unused)."""
    start = 0
    for length in lengths:
        if start >= n:
            return
        stop = min(start + int(length), n)
        yield start, stop
        start = stop
