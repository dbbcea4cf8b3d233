"""The replay's progress display, read from a real pseudo-terminal as a user sees it."""

from __future__ import annotations

import io
import os
import re
import select
import subprocess
import sys
import time
from pathlib import Path

import pytest

from vtolpose.service.cli import main
from vtolpose.service.replay.progress import Progress

PERCENT = re.compile(r"\]\s+([0-9.]+)%")


@pytest.fixture(scope="module")
def long_book(tmp_path_factory) -> Path:
    # Ten minutes: at ~400 × real time its replay still lasts over a second, ten redraws of the progress line.
    out = tmp_path_factory.mktemp("progress") / "book"
    assert main(["-q", "simulate", "--duration", "600", "--seed", "3", "--out", str(out), "--no-camera"]) == 0
    return out


def read_terminal(cmd: list[str], timeout_s: float = 120.0) -> list[tuple[float, str]]:
    """Run ``cmd`` with stderr on a pty; every chunk it draws, with its arrival time."""
    master, slave = os.openpty()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=slave, env={**os.environ, "COLUMNS": "150"})
    os.close(slave)
    started, chunks = time.monotonic(), []
    try:
        while time.monotonic() - started < timeout_s:
            ready, _, _ = select.select([master], [], [], 0.2)
            if ready:
                try:
                    data = os.read(master, 4096)
                except OSError:  # the child closed the terminal
                    break
                if not data:
                    break
                chunks.append((time.monotonic() - started, data.decode(errors="replace")))
            elif proc.poll() is not None:
                break
    finally:
        proc.wait(timeout=30)
        os.close(master)
    assert proc.returncode == 0
    return chunks


def test_progress_starts_at_once_and_counts_through_the_data(long_book):
    chunks = read_terminal([sys.executable, "-m", "vtolpose", "replay", str(long_book)])
    text = "".join(c for _, c in chunks)
    draws = [d for d in re.split(r"[\r\n]", text) if d.startswith("replay book")]
    assert draws and "reading the data" in draws[0]  # something on the screen before any work
    percents = [float(m.group(1)) for d in draws if (m := PERCENT.search(d))]
    assert percents[0] == 0.0 and percents[-1] == 100.0
    assert percents == sorted(percents)
    assert len({p for p in percents if 0.0 < p < 100.0}) >= 3, percents  # it moves through the data
    assert "nan" not in text
    etas = [d for d in draws if re.search(r"eta \d+ (s|min)", d)]
    assert etas, "no ETA ever shown"
    assert "done in" in draws[-1]


def test_eta_waits_for_enough_work_then_follows_the_average_rate():
    now = [0.0]
    progress = Progress(100.0, "x", stream=io.StringIO(), enabled=True, clock=lambda: now[0])
    now[0] = 0.3
    assert "eta --" in progress.line(50.0)  # too early to say
    now[0] = 2.0
    assert "eta --" in progress.line(0.5)  # too little done to say
    assert "eta 2 s" in progress.line(50.0)  # half done in 2 s: 2 s to go
    now[0] = 120.0
    assert "eta 3 min 00 s" in progress.line(40.0)
    assert "done in 2 min 00 s" in progress.line(100.0)


def test_progress_is_silent_off_a_terminal(long_book, capfd):
    assert main(["-q", "replay", str(long_book)]) == 0
    assert "replay book" not in capfd.readouterr().err


def test_the_first_draw_that_knows_the_total_is_never_skipped():
    """'reading the data' first; the 0 % line right after it, however fast the data were read."""
    now = [0.0]
    out = io.StringIO()
    progress = Progress(None, "x", stream=out, enabled=True, clock=lambda: now[0])
    now[0] = 0.01
    progress.total = 10.0
    progress.update(0.0)
    progress.update(0.5)  # within 0.1 s of the last draw: skipped
    draws = [d for d in out.getvalue().split("\r") if d]
    assert "reading the data" in draws[0] and len(draws) == 2 and PERCENT.search(draws[1]).group(1) == "0.0"
