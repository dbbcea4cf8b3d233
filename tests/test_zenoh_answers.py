"""The query process's copy of the pose history (service/outputs/zenoh_answers.py): fed one way, never waiting,
answering what the service's own history answers, to the byte."""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest

from vtolpose.estimator import ROW, OutsideHistory, PoseHistory
from vtolpose.estimator.core.rotation import quat_from_euler
from vtolpose.service.outputs.zenoh_answers import (HistoryCopy, HistoryFeed, QueryProcess, QueryProcessGone,
                                                    answer_text)

MS = 1_000_000
ORIGIN = (59.9, 10.7, 120.0)


def row(rng: np.random.Generator) -> np.ndarray:
    q = quat_from_euler(*rng.uniform(-0.5, 0.5, 3))
    cov = np.diag(rng.uniform(1e-4, 1e-2, 6))
    return PoseHistory.make_row(rng.normal(size=3), q, rng.normal(size=3), rng.normal(size=3), cov)


def operations(seed: int, n: int = 1500) -> list[tuple]:
    """A runtime's history calls: predictions ahead, fused poses behind them, now and then a smoothed run."""
    rng = np.random.default_rng(seed)
    ops: list[tuple] = []
    fused_t = predicted_t = 0
    for k in range(n):
        predicted_t += 8 * MS
        ops.append(("predicted", predicted_t, row(rng)))
        if k % 2 == 0 and fused_t + 100 * MS < predicted_t:
            fused_t += 20 * MS
            ops.append(("fused", fused_t, row(rng)))
        if k % 97 == 50:
            times = np.arange(fused_t - 400 * MS, fused_t - 100 * MS, 12 * MS, dtype=np.int64)  # > 4 KiB: cut by a pipe
            ops.append(("smoothed", times, np.array([row(rng) for _ in times])))
    return ops


def apply(history: PoseHistory, feed: HistoryFeed | None, op: tuple) -> None:
    kind, t, rows = op
    getattr(history, f"add_{kind}")(t, rows)
    if feed is not None:
        getattr(feed, kind)(t, rows)


def answers(history: PoseHistory, t_first: int, t_last: int) -> list[str]:
    """Every kind of answer over the history's span, and the refusals, as text."""
    out = []
    for t in np.linspace(t_first - 50 * MS, t_last + 50 * MS, 23).astype(np.int64):
        for kind, args in (("pose/at", (int(t),)), ("trajectory", (int(t) - 300 * MS, int(t)))):
            try:
                out.append(answer_text(history, kind, args, ORIGIN))
            except OutsideHistory as exc:
                out.append(f"outside: {exc}")
    return out


def test_the_copy_answers_what_the_history_answers_whatever_the_cut():
    """Frames read in pieces of any size (a pipe's reads) build the same history, to the byte of every answer."""
    history, ops = PoseHistory(2.0), operations(1)
    read, write = os.pipe()
    feed, copy = HistoryFeed(write), HistoryCopy(2.0)
    rng = np.random.default_rng(2)
    for op in ops:
        apply(history, feed, op)
        data = os.read(read, 1 << 20)
        cut = int(rng.integers(0, len(data) + 1))  # frames split across reads
        copy.take(data[:cut])
        copy.take(data[cut:])
    os.close(read)
    os.close(write)
    bounds = history.bounds()
    assert copy.history.bounds() == bounds
    assert len(copy.history) == len(history)
    assert answers(copy.history, *bounds) == answers(history, *bounds)
    kinds = set()
    for text in answers(history, *bounds):
        if text.startswith("{"):
            kind = json.loads(text)["kind"]
            kinds.update(kind if isinstance(kind, list) else [kind])
    assert kinds >= {"predicted", "filtered", "smoothed"}  # all three kinds went through the feed


def test_a_full_pipe_never_makes_the_sender_wait_and_the_copy_starts_again():
    """Nobody reads: sends return at once, frames wait in the feed up to its bound, then whole frames are dropped and
    a reset goes ahead of the next; the copy, read then, holds what came after the reset, nothing interpolated
    across the hole."""
    history, ops = PoseHistory(60.0), operations(3, n=4000)
    read, write = os.pipe()
    feed = HistoryFeed(write, bound_bytes=200_000)
    for op in ops[:3000]:
        apply(history, feed, op)
        assert feed.pending_bytes() <= 200_000 + 20_000  # one frame over the bound at most, never more
    assert feed.dropped > 0 and not feed.broken
    copy = HistoryCopy(60.0)
    os.set_blocking(read, False)
    for op in ops[3000:]:
        apply(history, feed, op)
        drain(read, copy)
    assert feed.pending_bytes() == 0
    assert copy.resets >= 1 and feed.resets >= 1
    first, last = copy.history.bounds()
    assert last == history.bounds()[1]
    assert first > history.bounds()[0]  # the time before the reset is not claimed
    inside = [a for a in answers(history, first + 400 * MS, last) if not a.startswith("outside")]
    assert len(inside) > 30
    assert [a for a in answers(copy.history, first + 400 * MS, last) if not a.startswith("outside")] == inside
    os.close(read)
    os.close(write)


def drain(fd: int, copy: HistoryCopy) -> None:
    while True:
        try:
            data = os.read(fd, 1 << 16)
        except BlockingIOError:
            return
        copy.take(data)


def test_one_row_frames_are_the_general_frames():
    from vtolpose.service.outputs.zenoh_answers import PREDICTED, frame, frame_one

    r = row(np.random.default_rng(7))
    assert frame_one(PREDICTED, 123456789012, r) == frame(PREDICTED, 123456789012, r[None, :])


def test_a_frame_the_pipe_takes_in_part_is_finished_before_the_next():
    """A smoothed run larger than the pipe goes in pieces; the frames after it wait behind its rest, and the copy
    reads the same history."""
    import fcntl

    read, write = os.pipe()
    fcntl.fcntl(write, getattr(fcntl, "F_SETPIPE_SZ", 1031), 4096)
    os.set_blocking(read, False)
    feed, copy, history = HistoryFeed(write), HistoryCopy(5.0), PoseHistory(5.0)
    rng = np.random.default_rng(8)
    for k in range(1, 200):
        apply(history, feed, ("fused", k * 10 * MS, row(rng)))
        drain(read, copy)
        feed.flush()
    drain(read, copy)
    assert feed.pending_bytes() == 0
    times = np.arange(100 * MS, 1_900 * MS, 10 * MS, dtype=np.int64)  # 180 rows, ~72 KB
    apply(history, feed, ("smoothed", times, np.array([row(rng) for _ in times])))
    assert feed.pending_bytes() > 0 and feed._started  # the pipe took the first piece only
    for k in range(200, 260):
        apply(history, feed, ("predicted", k * 10 * MS, row(rng)))
        drain(read, copy)
    while feed.pending_bytes():
        feed.flush()  # nothing new: what waits goes on as the pipe empties
        drain(read, copy)
    assert copy.resets == 0 and feed.dropped == 0
    bounds = history.bounds()
    assert answers(copy.history, *bounds) == answers(history, *bounds)
    os.close(read)
    os.close(write)


def test_a_closed_reader_breaks_the_feed_without_an_error():
    read, write = os.pipe()
    feed = HistoryFeed(write)
    os.close(read)
    feed.predicted(1, np.zeros(ROW))
    assert feed.broken
    feed.fused(2, np.zeros(ROW))  # nothing raised, nothing kept
    assert feed.pending_bytes() == 0
    os.close(write)


@pytest.fixture
def process():
    answers_process = QueryProcess(2.0)
    answers_process.start()
    yield answers_process
    answers_process.close()


def test_the_process_answers_as_the_service_would(process):
    history, ops = PoseHistory(2.0), operations(4, n=600)
    for op in ops:
        apply(history, process.feed, op)
    first, last = history.bounds()
    for t in np.linspace(first - 50 * MS, last + 50 * MS, 11).astype(np.int64):
        for kind, args in (("pose/at", (int(t),)), ("trajectory", (int(t) - 300 * MS, int(t)))):
            try:
                expected = answer_text(history, kind, args, ORIGIN).encode()
            except OutsideHistory as exc:
                with pytest.raises(OutsideHistory, match="outside the history|does not overlap"):
                    process.ask(kind, args, ORIGIN)
                assert str(exc)
                continue
            assert process.ask(kind, args, ORIGIN) == expected
    assert process.alive


def test_a_dead_process_is_reported_and_stays_stopped(process):
    history = PoseHistory(2.0)
    apply(history, process.feed, ("predicted", 10 * MS, row(np.random.default_rng(5))))
    assert process.ask("pose/at", (10 * MS,), None)
    os.kill(process.pid, 9)
    deadline = time.monotonic() + 10.0
    while process.alive and time.monotonic() < deadline:
        time.sleep(0.05)
    with pytest.raises(QueryProcessGone):
        process.ask("pose/at", (10 * MS,), None)
    apply(history, process.feed, ("predicted", 20 * MS, row(np.random.default_rng(6))))  # the runtime goes on
    assert not process.alive


@pytest.mark.slow
def test_the_daemon_answers_from_the_query_process_and_itself_once_it_is_gone(tmp_path):
    """Through the daemon over Zenoh on loopback: the answers come from the query process (its count), equal to the
    service's own history's; with the process killed, the service answers the same window itself."""
    import asyncio
    import threading

    from vtolpose.config import load_config
    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.drivers.simulator import simulate_flight
    from vtolpose.drivers.simulator.export import write_flight
    from vtolpose.service.runtime.daemon import build_runtime, serve
    from vtolpose.service.runtime.sources import ReplayClock, ReplaySource

    from conftest import free_port, pose_client_when_listening

    write_flight(simulate_flight("book", 8.0, 4), tmp_path / "book")
    dataset = Dataset.open(tmp_path / "book")
    port = free_port()
    cfg = load_config(None, {"outputs": {"zenoh": {"enabled": True, "listen": [f"tcp/127.0.0.1:{port}"]}}})
    runtime = build_runtime(cfg, dataset.calibration)
    output = next(o for o in runtime.outputs if o.name == "zenoh")
    assert output.answers is not None and runtime.history_feed is output.answers.feed
    service = threading.Thread(target=lambda: asyncio.run(serve(
        runtime, [ReplaySource(dataset, ["imu", "gps"], ReplayClock(1.0))], 8.0, handle_signals=False)), daemon=True)
    t0 = int(dataset.imu_raw().t_ns[0])  # before the service reads the dataset on its thread
    service.start()
    window_ns = (t0 + 3_000_000_000, t0 + 3_500_000_000)  # final long before it is asked for
    deadline = time.monotonic() + 10.0
    client = pose_client_when_listening(port)
    with client:
        while time.monotonic() < deadline + 5.0:
            newest = runtime.history.bounds()
            if newest is not None and newest[1] > window_ns[1] + 1_000_000_000:
                break
            time.sleep(0.1)
        elsewhere = client.trajectory(*window_ns)
        assert output.stats["answered_elsewhere"] >= 1
        assert output.link_stats()["query_process"] == "running"
        with runtime.history_lock:
            own = runtime.history.window(*window_ns)
        np.testing.assert_array_equal(elsewhere.t_ns, own.t_ns)
        np.testing.assert_array_equal(elsewhere.p, own.p)
        np.testing.assert_array_equal(elsewhere.cov, own.cov)
        os.kill(output.answers.pid, 9)
        here = client.trajectory(*window_ns)
        assert output.answers is None  # found gone on that query, answered here from then on
        assert runtime.status_document()["outputs"]["zenoh"]["query_process"] == "gone"
        np.testing.assert_array_equal(here.t_ns, elsewhere.t_ns)
        np.testing.assert_array_equal(here.p, elsewhere.p)
        np.testing.assert_array_equal(here.q, elsewhere.q)
    service.join(15.0)
