"""The answers to ``pose/at`` and ``trajectory``, and a process of their own that makes them.

A ten-second window is ~0.8 MB of JSON. Made in the service's process, even in pieces with the
interpreter handed back between them, a flood of such queries delays the poses by tens of
milliseconds (``vtolpose bench --only zenoh-queries``); the same answers made elsewhere cost the
pose path next to nothing. So by default (``outputs.zenoh.query_process``) the windows are made in a
niced process that keeps a copy of the pose history (a ``pose/at`` answer, ~1 KB, is cheaper made on
the service's thread than sent across):

- the runtime sends every change it makes to its own history down a pipe (:class:`HistoryFeed`):
  one way, never waiting — while the pipe is full the frames queue up to a bound, then the oldest
  whole frames are dropped and the copy is told to start again (``reset``), so that it never
  interpolates across a hole;
- the service's query thread hands each query over and passes the answer (bytes) on to Zenoh;
- the copy takes the same operations in the same order, so it answers what the service's own
  history would, to the byte (``tests/test_zenoh_answers.py``).

If the process dies or stops answering, the service answers in its own process again.
"""

from __future__ import annotations

import json
import logging
import multiprocessing
import os
import struct
import time
from collections import deque
from contextlib import nullcontext
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from vtolpose.estimator import ROW, OutsideHistory, PoseHistory, PoseWindow
from vtolpose.service.outputs.pose_json import Origin, origin_json

log = logging.getLogger(__name__)

JSON_CHUNK_ROWS = 128  # rows serialised at a time when answering a trajectory (well under 1 ms each)
WORKER_NICE = 10
WORKER_DUTY = 0.25  # the answering rests 3x its CPU time: at most a quarter of a core, whatever the load

# History operations as frames: length (uint32), operation (uint8), row count (uint32), times (int64 × n),
# rows (float64 × n × ROW). FUSED and PREDICTED carry one row, SMOOTHED a run, RESET none.
FUSED, PREDICTED, SMOOTHED, RESET = 1, 2, 3, 4
_LENGTH = struct.Struct("<I")
_HEAD = struct.Struct("<BI")
PIPE_BYTES = 1 << 20  # asked of the kernel for the feed's pipe (Linux allows 1 MiB by default)
FEED_BOUND_BYTES = 16 << 20  # frames queued in the service while the pipe is full; beyond: dropped, copy reset
ANSWER_TIMEOUT_S = 5.0  # no answer for this long: the process is taken as hung and the service answers itself


def _floats(values: np.ndarray) -> list:
    """A plain list for JSON; non-finite numbers become null (JSON has no NaN)."""
    finite = np.isfinite(values)
    if finite.all():
        return values.tolist()
    return np.where(finite, values, None).tolist()


def _rows_json(values: np.ndarray) -> str:
    """A JSON array of ``values``' rows, written JSON_CHUNK_ROWS at a time with the interpreter
    handed back between pieces (``json.dumps`` keeps it for the whole of one call)."""
    parts = []
    for k in range(0, len(values), JSON_CHUNK_ROWS):
        parts.append(json.dumps(_floats(values[k:k + JSON_CHUNK_ROWS]))[1:-1])
        time.sleep(0)
    return "[" + ",".join(p for p in parts if p) + "]"


def trajectory_json(window: PoseWindow, origin: Origin) -> str:
    """The ``<prefix>/trajectory`` answer, as :func:`json.dumps` of the same document would write it."""
    head = json.dumps({"frame": "NED", "origin": origin_json(origin), "t_ns": window.t_ns.tolist()})[:-1]
    fields = ", ".join(f'"{name}": {_rows_json(values)}' for name, values in
                       (("p", window.p), ("q", window.q), ("v", window.v), ("w", window.w),
                        ("cov", window.cov.reshape(-1, 36))))
    return (f'{head}, {fields}, "fused": {json.dumps(window.fused.tolist())}, '
            f'"kind": {json.dumps(window.kind.tolist())}}}')


def answer_text(history: PoseHistory, kind: str, args: tuple[int, ...], origin: Origin, lock: Any = None) -> str:
    """The answer to a checked query (``kind`` pose/at or trajectory); OutsideHistory if there is none.
    ``lock``: held while reading ``history``, not while writing the text."""
    if kind == "pose/at":
        with lock if lock is not None else nullcontext():
            pose = history.at(args[0])
        return json.dumps({
            "t_ns": pose.t_ns, "frame": "NED", "origin": origin_json(origin),
            "p": _floats(pose.p), "q": _floats(pose.q), "v": _floats(pose.v), "w": _floats(pose.w),
            "cov": _floats(pose.cov.reshape(36)), "fused": pose.fused, "kind": pose.kind,
        })
    with lock if lock is not None else nullcontext():
        window = history.window(*args)
    return trajectory_json(window, origin)


# ----------------------------------------------------------------------------------- the feed
def frame(op: int, t_ns: np.ndarray | int = 0, rows: np.ndarray | None = None) -> bytes:
    """One history operation as the feed sends it."""
    times = np.atleast_1d(np.asarray(t_ns, dtype="<i8"))
    body = b"" if rows is None else times.tobytes() + np.ascontiguousarray(rows, dtype="<f8").tobytes()
    n = 0 if rows is None else times.size
    payload = _HEAD.pack(op, n) + body
    return _LENGTH.pack(len(payload)) + payload


_ONE = struct.Struct("<IBIq")  # length, operation, one row, its time: :func:`frame` of one row, made cheaper


def frame_one(op: int, t_ns: int, row: np.ndarray) -> bytes:
    """:func:`frame` of one row (float64, contiguous, as ``PoseHistory.make_row`` makes it): the per-pose case,
    made with one numpy call instead of five (each costs tens of microseconds on a paced loop)."""
    body = row.tobytes()
    return _ONE.pack(len(body) + _ONE.size - _LENGTH.size, op, 1, t_ns) + body


class HistoryFeed:
    """The service's end of the feed: every change to its history, sent without ever waiting.

    Frames the pipe cannot take now wait here, in order, and go first at the next send; past
    ``bound_bytes`` the waiting whole frames are dropped (``dropped`` counts them) and a RESET takes
    their place. Broken (the process is gone): sends do nothing."""

    def __init__(self, fd: int, bound_bytes: int = FEED_BOUND_BYTES) -> None:
        self.fd = fd
        os.set_blocking(fd, False)
        self.bound_bytes = bound_bytes
        self._waiting: deque[memoryview] = deque()
        self._waiting_bytes = 0
        self._started = False  # the pipe has taken part of the first waiting frame: the rest must follow
        self.dropped = 0
        self.resets = 0
        self.broken = False

    def fused(self, t_ns: int, row: np.ndarray) -> None:
        self.send(frame_one(FUSED, t_ns, row))

    def predicted(self, t_ns: int, row: np.ndarray) -> None:
        self.send(frame_one(PREDICTED, t_ns, row))

    def smoothed(self, t_ns: np.ndarray, rows: np.ndarray) -> None:
        self.send(frame(SMOOTHED, t_ns, rows))

    def send(self, data: bytes) -> None:
        if self.broken:
            return
        if not self._waiting:  # the usual case: straight into the pipe
            n = self._write(data)
            if n is None or n == len(data):
                return
            self._waiting.append(memoryview(data)[n:])
            self._waiting_bytes += len(data) - n
            self._started = n > 0
            return
        self._waiting.append(memoryview(data))
        self._waiting_bytes += len(data)
        self.flush()
        if self._waiting_bytes > self.bound_bytes:
            self._drop()

    def _write(self, data: memoryview | bytes) -> int | None:
        """Bytes the pipe took (0 when full); None once the reading end is gone."""
        try:
            return os.write(self.fd, data)
        except BlockingIOError:
            return 0
        except OSError as exc:  # the reading end is closed: the process is gone
            log.warning("pose history feed to the query process closed (%s): it is no longer fed", exc)
            self.broken = True
            self._waiting.clear()
            self._waiting_bytes = 0
            return None

    def flush(self) -> None:
        """What waits, into the pipe as far as it takes it (each send does this first)."""
        while self._waiting:
            head = self._waiting[0]
            n = self._write(head)
            if n is None:
                return
            self._waiting_bytes -= n
            if n < len(head):
                self._waiting[0] = head[n:]
                self._started = self._started or n > 0
                return
            self._waiting.popleft()
            self._started = False

    def _drop(self) -> None:
        """Drop every waiting frame but the rest of one the pipe has begun to take; a RESET follows it, so that
        the copy starts again after the hole."""
        keep = self._waiting[0] if self._started else None
        self.dropped += len(self._waiting) - (keep is not None)
        self._waiting.clear()
        self._waiting_bytes = 0
        for data in ([keep] if keep is not None else []) + [memoryview(frame(RESET))]:
            self._waiting.append(data)
            self._waiting_bytes += len(data)
        self.resets += 1

    def pending_bytes(self) -> int:
        return self._waiting_bytes


class HistoryCopy:
    """The other end: a :class:`PoseHistory` that takes the feed's frames as they come."""

    def __init__(self, span_s: float) -> None:
        self.span_s = span_s
        self.history = PoseHistory(span_s)
        self._buffer = bytearray()
        self.resets = 0

    def take(self, data: bytes) -> None:
        """Bytes read from the feed (any cut): each whole frame applied in order, the rest kept."""
        buffer = self._buffer
        buffer += data
        at = 0
        while len(buffer) - at >= _LENGTH.size:
            n = _LENGTH.unpack_from(buffer, at)[0]
            if len(buffer) - at - _LENGTH.size < n:
                break
            self._apply(memoryview(buffer)[at + _LENGTH.size: at + _LENGTH.size + n])
            at += _LENGTH.size + n
        del buffer[:at]

    def _apply(self, payload: memoryview) -> None:
        op, n = _HEAD.unpack_from(payload)
        times = np.frombuffer(payload, dtype="<i8", count=n, offset=_HEAD.size)
        rows = np.frombuffer(payload, dtype="<f8", count=n * ROW, offset=_HEAD.size + 8 * n).reshape(n, ROW)
        if op == FUSED:
            self.history.add_fused(int(times[0]), rows[0].copy())
        elif op == PREDICTED:
            self.history.add_predicted(int(times[0]), rows[0].copy())
        elif op == SMOOTHED:
            self.history.add_smoothed(times.copy(), rows.copy())
        elif op == RESET:
            self.history = PoseHistory(self.span_s)
            self.resets += 1
        else:
            raise ValueError(f"pose history feed: unknown operation {op}")


# ------------------------------------------------------------------------------ the process
def _drain(fd: int, copy: HistoryCopy) -> bool:
    """Everything the feed holds now, applied; False once the service has closed it."""
    while True:
        try:
            data = os.read(fd, PIPE_BYTES)
        except BlockingIOError:
            return True
        if not data:
            return False
        copy.take(data)


def serve_answers(requests: Connection, feed: Connection, span_s: float, duty: float = WORKER_DUTY) -> None:
    """The query process: keep the copy fed, answer each request (kind, args, origin) with
    b"+" and the answer, or b"-" and why there is none; rest ``1/duty - 1`` times each answer's CPU time."""
    try:  # normal scheduling (never the loop's SCHED_FIFO, which a spawned process inherits), niced
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        os.setpriority(os.PRIO_PROCESS, 0, WORKER_NICE)
    except (AttributeError, OSError) as exc:
        log.debug("query process priority not set: %s", exc)
    copy, fd = HistoryCopy(span_s), feed.fileno()
    os.set_blocking(fd, False)
    fed = True
    while True:
        if fed:
            fed = _drain(fd, copy)
        if not requests.poll(0.05):
            continue
        try:
            request = requests.recv()
        except (EOFError, OSError):
            return
        if request is None:
            return
        kind, args, origin = request
        started = time.thread_time()
        if fed:
            fed = _drain(fd, copy)
        try:
            answer = b"+" + answer_text(copy.history, kind, tuple(args), origin).encode()
        except OutsideHistory as exc:
            answer = b"-" + str(exc).encode()
        try:
            requests.send_bytes(answer)
        except OSError:  # the service has gone
            return
        time.sleep((time.thread_time() - started) * (1.0 / duty - 1.0))


class QueryProcessGone(RuntimeError):
    """The query process died or stopped answering."""


class QueryProcess:
    """The service's handle on the query process: the feed to give the runtime, and :meth:`ask`."""

    def __init__(self, span_s: float, duty: float = WORKER_DUTY, bound_bytes: int = FEED_BOUND_BYTES) -> None:
        self.span_s, self.duty = span_s, duty
        read_end, write_end = multiprocessing.Pipe(duplex=False)
        self._feed_read, self._feed_write = read_end, write_end
        try:
            import fcntl

            fcntl.fcntl(write_end.fileno(), getattr(fcntl, "F_SETPIPE_SZ", 1031), PIPE_BYTES)
        except (ImportError, OSError) as exc:  # the kernel's default (64 KiB) then: frames wait in the feed
            log.debug("query process pipe left at its default size: %s", exc)
        self.feed = HistoryFeed(write_end.fileno(), bound_bytes)
        self._requests: Connection | None = None
        self._process: multiprocessing.process.BaseProcess | None = None

    def start(self) -> None:
        ours, theirs = multiprocessing.Pipe(duplex=True)
        context = multiprocessing.get_context("spawn")  # never fork a process that runs Zenoh's threads
        self._process = context.Process(target=serve_answers, args=(theirs, self._feed_read, self.span_s, self.duty),
                                        name="vtolpose-queries", daemon=True)
        self._process.start()
        theirs.close()
        self._feed_read.close()  # the child holds its own copy
        self._requests = ours

    @property
    def alive(self) -> bool:
        return self._process is not None and self._process.is_alive() and not self.feed.broken

    @property
    def pid(self) -> int | None:
        return None if self._process is None else self._process.pid

    def ask(self, kind: str, args: tuple[int, ...], origin: Origin) -> bytes:
        """The answer's text (UTF-8); OutsideHistory where there is none; QueryProcessGone if the process
        cannot answer (then it is stopped for good)."""
        if self._requests is None or not self.alive:
            raise QueryProcessGone("the query process is not running")
        try:
            self._requests.send((kind, args, origin))
            if not self._requests.poll(ANSWER_TIMEOUT_S):
                raise QueryProcessGone(f"the query process did not answer within {ANSWER_TIMEOUT_S:g} s")
            answer = self._requests.recv_bytes()
        except (EOFError, OSError) as exc:
            self.close()
            raise QueryProcessGone(f"the query process is gone ({exc})") from None
        except QueryProcessGone:
            self.close()
            raise
        if answer[:1] == b"-":
            raise OutsideHistory(answer[1:].decode())
        return answer[1:]

    def close(self) -> None:
        """Stop the process (asked first, then killed) and the feed. The feed's pipe end is not closed here: this
        may run on the query thread while the loop is writing to it, and a closed descriptor's number can be
        reused; it closes with this object."""
        requests, self._requests = self._requests, None
        if requests is not None:
            try:
                requests.send(None)
            except OSError as exc:  # already gone: nothing to ask, the join below finds it ended
                log.debug("query process gone before it was asked to stop: %s", exc)
            requests.close()
        process = self._process
        if process is not None:
            process.join(timeout=2.0)
            if process.is_alive():
                process.kill()
                process.join(timeout=2.0)
        self.feed.broken = True
