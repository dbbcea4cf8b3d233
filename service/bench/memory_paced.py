"""Memory of a paced run: does anything grow once the pose history is full?

A landfill flight is replayed in real time (``--speed 1``) through the runtime with both outputs
on, for ``minutes``. Resident memory (RSS, less what tracemalloc itself holds) and the memory
Python allocated (tracemalloc, one frame per allocation) are sampled every minute; at the end the
allocation sites that grew most since the history filled are listed. Figures: growth per minute
over the first and the second half of the time after the fill.

What it shows. ``--rss-only``, 20 min: RSS 197 → 213 MB from minute 2 to 11 (1.7
MB/min), then flat to the end. Traced, one hour: Python's allocations flat (121.52 → 121.53 MB
from minute 4 to 59), and the one site that grew is the pose history's array
(estimator/pose_history.py, +6.4 MB): once the history holds more than half its buffer, the
buffer doubles (np.zeros, whose pages the kernel maps only when first written), and each new row
touches fresh memory until the write position reaches the end and slides back to the start.
Bounded by that buffer (13 MB at 125 Hz and 120 s of history): not a leak. Whether RSS shows it
depends on what the allocator can reuse (in the traced run, RSS stayed at 698 MB throughout).

Run: ``vtolpose bench --only memory-paced`` (an hour) or
``python -m vtolpose.service.bench.memory_paced MINUTES [--rss-only]``.
"""

from __future__ import annotations

import asyncio
import socket
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path
from typing import Callable

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.service.runtime.replay_feed import replay_async
from vtolpose.service.runtime.status import resident_memory_mb
from vtolpose.service.runtime.wiring import config_sections

Row = tuple[str, float, str, str]


def _free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _slope(samples: list[tuple[float, float]]) -> float:
    """Growth per minute between the first and the last sample."""
    (t0, m0), (t1, m1) = samples[0], samples[-1]
    return (m1 - m0) / max((t1 - t0) / 60.0, 1e-9)


def bench_memory_paced(minutes: float = 60.0, echo: Callable[[str], None] = print, trace: bool = True) -> list[Row]:
    """RSS and Python allocations per minute of a paced replay with both outputs, after the history fills.

    ``trace`` False: RSS only, without tracemalloc (whose own allocations change what the allocator reuses)."""
    cfg = load_config(None, {"outputs": {
        "mavlink": {"enabled": True, "url": f"udpout:127.0.0.1:{_free_port(socket.SOCK_DGRAM)}"},
        "zenoh": {"enabled": True, "listen": [f"tcp/127.0.0.1:{_free_port()}"]}}})
    fill_s = config_sections(cfg).outputs.zenoh.history_s + 30.0
    rss: list[tuple[float, float]] = []
    traced: list[tuple[float, float]] = []
    top: list[str] = []

    async def probe(t0: float) -> None:
        base = None  # two snapshots only (at the fill and near the end): taking them churns memory too
        while True:
            await asyncio.sleep(60.0)
            el = time.monotonic() - t0
            r = resident_memory_mb() - tracemalloc.get_tracemalloc_memory() / 1e6
            p = tracemalloc.get_traced_memory()[0] / 1e6
            echo(f"  [{el / 60:5.1f} min] RSS {r:7.1f} MB, Python allocations {p:6.2f} MB")
            if el < fill_s or top:
                continue
            if trace and base is None:  # the snapshot's own memory shows from the next sample on
                base = tracemalloc.take_snapshot()
                continue
            rss.append((el, r))
            traced.append((el, p))
            if trace and el >= minutes * 60.0 - 90.0:  # the last sample: nothing after the second snapshot
                top[:] = [str(s) for s in tracemalloc.take_snapshot().compare_to(base, "lineno")[:3]]

    async def run(root: Path) -> None:
        task = asyncio.create_task(probe(time.monotonic()))
        await replay_async(Dataset.open(root), cfg, speed=1.0, duration_s=minutes * 60.0, handle_signals=False)
        task.cancel()

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "landfill"
        # Simulated in another process, so that this one holds only what a run holds.
        subprocess.run([sys.executable, "-m", "vtolpose", "-q", "simulate", "--scenario", "landfill", "--duration",
                        str(minutes * 60.0 + 60.0), "--seed", "3", "--no-camera", "--out", str(root)],
                       check=True, capture_output=True)
        if trace:
            tracemalloc.start(1)
        try:
            asyncio.run(run(root))
        finally:
            tracemalloc.stop()
    half = len(rss) // 2
    rows: list[Row] = []
    if half >= 1:
        rows += [("RSS growth, first half after the fill", _slope(rss[: half + 1]), "MB/min", f"{len(rss)} samples"),
                 ("RSS growth, second half", _slope(rss[half:]), "MB/min", ""),
                 ("Python allocations growth, second half", _slope(traced[half:]), "MB/min", "" if trace else "not traced")]
    rows += [(f"grew most: {line}", 0.0, "", "") for line in top]
    return rows


if __name__ == "__main__":
    minutes = float(sys.argv[1]) if len(sys.argv) > 1 and not sys.argv[1].startswith("-") else 60.0
    for label, value, unit, note in bench_memory_paced(minutes, trace="--rss-only" not in sys.argv):
        print(f"  {label:<60} {value:>8.3f} {unit:<7} {note}")
