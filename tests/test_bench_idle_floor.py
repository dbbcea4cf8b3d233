"""The runtime-latency bench's idle floor: only the work is timed, after each kind of wait."""

import time

from vtolpose.service.bench.runtime import after_idle_us, idle_floor_rows


def test_only_the_work_is_timed_after_each_wait():
    gap_s, work_s = 0.02, 0.002
    calls = []

    def work() -> None:
        calls.append(time.perf_counter())
        time.sleep(work_s)

    warm, slept, spun = after_idle_us(work, gap_s, count=5)
    assert len(calls) == 3 * 6  # each kind: one call to warm up, then ``count`` timed
    for p50 in (warm, slept, spun):
        assert work_s * 1e6 <= p50 < (work_s + 0.5 * gap_s) * 1e6  # the work's time, never the gap's
    # The waits happen: the timed calls after a sleep or a spin are at least a gap apart; the warm ones are not.
    starts = [calls[1:6], calls[7:12], calls[13:18]]
    assert max(b - a for a, b in zip(starts[0], starts[0][1:])) < gap_s
    for kind in starts[1:]:
        assert min(b - a for a, b in zip(kind, kind[1:])) >= gap_s + work_s


def test_the_rows_say_the_ratios_of_their_own_figures():
    rows = idle_floor_rows(gap_s=0.001, count=20)
    (_, warm, unit, _), (_, slept, _, slept_note), (_, spun, _, spun_note) = rows
    assert unit == "us" and warm > 0.0 and slept > 0.0 and spun > 0.0
    assert slept_note.startswith(f"{slept / warm:.2f}x") and spun_note.startswith(f"{spun / warm:.2f}x")
    assert "1 ms" in rows[1][0] and "1 ms" in rows[2][0]
