"""Zenoh outputs for the LIDAR mapper and anyone else (INTERFACES.md, "Out: Zenoh"; docs/zenoh.md).

``<prefix>/pose`` carries every estimate, ``<prefix>/status`` a status document once a second;
the queryables ``<prefix>/pose/at?t_ns=…`` and ``<prefix>/trajectory?from=…;to=…`` answer from
the bounded pose history, each pose saying its ``kind`` (predicted, filtered, or smoothed once
the fixed lag has passed). An unanswerable query (time outside the history, a malformed
parameter, a window longer than ``max_window_s``, too many waiting) gets an error reply, never
silence. The session declares the liveliness token ``<prefix>/service/<zid>`` by which clients
know this session's answers and poses from anyone else's.

Query work never delays a pose: Zenoh's threads only check a query's parameters and queue it
(bounded, ``max_pending``); one niced thread takes them in turn. It hands each trajectory to the
query process (``outputs.zenoh.query_process``, :mod:`zenoh_answers`), which keeps a copy of the
pose history and makes the answer's JSON on its own interpreter, and passes the bytes on; a
``pose/at`` (~1 KB) it answers itself, as it does everything without that process (switched off,
or dead), reading the history under the lock the runtime takes for a moment per pose and writing
large answers in pieces. Either works at most a quarter of the time (WORKER_DUTY): a flood of the
largest windows fills the queue and gets "busy" replies, not more of the CPU. Poses go out at Zenoh's
real-time priority, ahead of answers in a link's queues, and each client link may ask at most
``max_queries_per_s`` per queryable (Zenoh's downsampling drops the excess; the client asks again).
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import queue
import re
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import zenoh

from vtolpose.config.sections import ZenohSection
from vtolpose.estimator import OutputPose, OutsideHistory, PoseHistory
from vtolpose.service.outputs.pose_json import Origin, PoseJson
from vtolpose.service.outputs.zenoh_answers import WORKER_DUTY, WORKER_NICE, QueryProcess, QueryProcessGone, answer_text
from vtolpose.service.outputs.pose_json import pose_message, pose_status  # noqa: F401 - also imported from here
from vtolpose.service.outputs.zenoh_session import ZenohSettings, service_config

log = logging.getLogger(__name__)

JSON = zenoh.Encoding.APPLICATION_JSON
_INTEGER = re.compile(r"-?[0-9]{1,19}")  # nothing else: no sign '+', spaces, '_' or exponents
_INT64 = (-(1 << 63), (1 << 63) - 1)


@dataclass(frozen=True, slots=True)
class QueryLimits:
    """``outputs.zenoh.max_window_s``, ``max_queries_per_s``, ``max_pending_queries``; and ``max_wait_s``:
    a query that waited longer than this behind others is told busy, not worked on (the pose client has
    given up on it after its 2-s timeout, and an answer then only costs the loop's core)."""

    max_window_s: float = 10.0
    max_queries_per_s: float = 200.0
    max_pending: int = 64
    max_wait_s: float = 2.0

    @classmethod
    def from_section(cls, zenoh_section: ZenohSection) -> "QueryLimits":
        return cls(zenoh_section.max_window_s, zenoh_section.max_queries_per_s, zenoh_section.max_pending_queries)


def parse_time_parameter(parameters: Any, name: str) -> int:
    """``name`` as integer nanoseconds; ValueError (quoting at most 24 characters of it) otherwise."""
    text = parameters.get(name)
    if text is None:
        raise ValueError(f"missing parameter {name}=<t_ns> (integer nanoseconds)")
    if not _INTEGER.fullmatch(text) or not _INT64[0] <= int(text) <= _INT64[1]:
        shown = repr(text) if len(text) <= 24 else f"{text[:24]!r}… ({len(text)} characters)"
        raise ValueError(f"parameter {name}={shown} is not an integer nanosecond time (digits only, optional '-')")
    return int(text)


class ZenohOutput:
    """Publishers, queryables and a liveliness token on one Zenoh session."""

    name = "zenoh"

    def __init__(
        self,
        settings: ZenohSettings,
        prefix: str,
        history: PoseHistory,
        lock: threading.Lock,
        origin: Callable[[], Origin] = lambda: None,
        limits: QueryLimits = QueryLimits(),
        answers: QueryProcess | None = None,
    ) -> None:
        self.settings = settings
        self.prefix = prefix
        self.history = history
        self.lock = lock
        self.origin = origin
        self.limits = limits
        self.answers = answers  # the query process; None: answered here, on the query thread
        self._had_process = answers is not None
        self.session: zenoh.Session | None = None
        self._entities: list[Any] = []
        self._seq = 0
        self._pose_json = PoseJson()
        self._queries: queue.Queue = queue.Queue(maxsize=limits.max_pending)
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self.stats = {"poses_published": 0, "queries": 0, "query_errors": 0, "queries_busy": 0,
                      "answered_elsewhere": 0}

    def open(self) -> None:
        keys = [f"{self.prefix}/pose/at", f"{self.prefix}/trajectory"]
        self.session = s = zenoh.open(service_config(self.settings, self.prefix, keys, self.limits.max_queries_per_s))
        drop = zenoh.CongestionControl.DROP  # a slow subscriber must never stall the estimator
        self._pose_pub = s.declare_publisher(f"{self.prefix}/pose", encoding=JSON, congestion_control=drop, express=True,
                                             priority=zenoh.Priority.REAL_TIME)
        self._pose_id = self._pose_pub.id  # the publisher's for its life: asked once, not per pose
        self._status_pub = s.declare_publisher(f"{self.prefix}/status", encoding=JSON, congestion_control=drop)
        self._stop.clear()
        if self.answers is not None:
            self.answers.start()
        self._worker = threading.Thread(target=self._answer_queries, name="zenoh-queries", daemon=True)
        self._worker.start()
        self._entities = [
            self._pose_pub, self._status_pub,
            s.declare_queryable(keys[0], lambda q: self._on_query(q, "pose/at")),
            s.declare_queryable(keys[1], lambda q: self._on_query(q, "trajectory")),
            s.liveliness().declare_token(f"{self.prefix}/service/{s.zid()}"),
        ]
        hint = ""
        if self.settings.mode == "peer" and self.settings.listen:
            endpoint = re.sub(r"/(0\.0\.0\.0|\[::\]):", "/<this computer's address>:", self.settings.listen[0])
            hint = f"; a mapper connects with PoseClient({self.prefix!r}, connect=[{endpoint!r}])"
        log.info("Zenoh %s session %s: %s; publishing under %s/%s", self.settings.mode, s.zid(),
                 self.settings.endpoints_text(), self.prefix, hint)

    def close(self) -> None:
        for entity in self._entities:  # first: no new queries
            try:
                entity.undeclare()
            except zenoh.ZError as exc:  # the session is closing anyway; undeclare the rest
                log.debug("Zenoh undeclare on close: %s", exc)
        self._entities = []
        self._stop.set()
        if self._worker is not None:
            self._worker.join(timeout=5.0)
            self._worker = None
        self._refuse_waiting("the service is stopping")
        if self.answers is not None:
            self.answers.close()
        if self.session is not None:
            self.session.close()
            self.session = None

    def link_stats(self) -> dict[str, Any]:
        """The counters, and the query process: ``running``, ``gone`` (answered here since), or ``off``;
        with the history frames its feed had to drop while the process did not read (its copy then started again)."""
        answers = self.answers
        state = "off" if not self._had_process else "running" if answers is not None and answers.alive else "gone"
        doc: dict[str, Any] = {**self.stats, "query_process": state}
        if answers is not None:
            doc.update(history_frames_dropped=answers.feed.dropped, history_copy_resets=answers.feed.resets)
        return doc

    # --------------------------------------------------------------------- publications
    def publish(self, pose: OutputPose) -> None:
        if self.session is None:
            return
        self._seq = seq = self._seq + 1
        self._pose_pub.put(self._pose_json(pose, seq, self.origin()), source_info=zenoh.SourceInfo(self._pose_id, seq))
        self.stats["poses_published"] += 1

    def prepare(self, pose_cov: np.ndarray | None) -> None:
        """The next pose's covariance, ready after the previous pose left: its text written now (PoseJson.prepare)."""
        if self.session is not None:
            self._pose_json.prepare(pose_cov)

    def publish_status(self, status: dict[str, Any]) -> None:
        if self.session is not None:
            self._status_pub.put(json.dumps(status), source_info=zenoh.SourceInfo(self._status_pub.id, 0))

    async def serve(self, stop: asyncio.Event) -> None:
        await stop.wait()  # everything happens in callbacks and the query thread

    # ------------------------------------------------------------------------- queries
    def _error(self, query: zenoh.Query, message: str) -> None:
        self.stats["query_errors"] += 1
        try:
            query.reply_err(json.dumps({"error": message}), encoding=JSON)
        except zenoh.ZError as exc:  # the asker is gone
            log.debug("Zenoh error reply not sent: %s", exc)
        query.drop()

    def _on_query(self, query: zenoh.Query, kind: str) -> None:
        """On a Zenoh thread: check the parameters (cheap), then queue the work or refuse at once."""
        self.stats["queries"] += 1
        try:
            if kind == "pose/at":
                args: tuple[int, ...] = (parse_time_parameter(query.parameters, "t_ns"),)
            else:
                t0, t1 = parse_time_parameter(query.parameters, "from"), parse_time_parameter(query.parameters, "to")
                if t1 < t0:
                    raise ValueError(f"the window ends (to={t1}) before it starts (from={t0})")
                if (t1 - t0) * 1e-9 > self.limits.max_window_s:
                    raise ValueError(f"a window of {(t1 - t0) * 1e-9:.6g} s is longer than the {self.limits.max_window_s:g} s "
                                     "one query may span (outputs.zenoh.max_window_s): ask in pieces")
                args = (t0, t1)
        except ValueError as exc:
            self._error(query, str(exc))
            return
        try:
            self._queries.put_nowait((kind, query, args, time.monotonic()))
        except queue.Full:
            self.stats["queries_busy"] += 1
            self._error(query, f"busy: {self.limits.max_pending} queries are waiting; ask again later")

    def _answer_queries(self) -> None:
        """The query thread: niced, so that the event loop wins a contended core."""
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), WORKER_NICE)
        except (AttributeError, OSError) as exc:
            log.debug("query thread nice %d refused: %s", WORKER_NICE, exc)
        while not self._stop.is_set():
            try:
                kind, query, args, queued = self._queries.get(timeout=0.2)
            except queue.Empty:
                continue
            waited = time.monotonic() - queued
            if waited > self.limits.max_wait_s:
                self.stats["queries_busy"] += 1
                self._error(query, f"busy: this query waited {waited:.1f} s behind others; ask again later")
                continue
            started = time.thread_time()  # its own CPU time: waiting for the history lock is not work
            try:
                self._answer(query, kind, args)
            except OutsideHistory as exc:
                self._error(query, str(exc))
            except zenoh.ZError as exc:  # the asker is gone
                log.debug("Zenoh reply not sent: %s", exc)
            except Exception as exc:  # a bug here must not end the query thread
                log.exception("answering %s failed", kind)
                self._error(query, f"internal error: {type(exc).__name__}")
            finally:
                query.drop()  # the final answer: the asker stops waiting (idempotent)
            self._stop.wait((time.thread_time() - started) * (1.0 / WORKER_DUTY - 1.0))

    def _answer(self, query: zenoh.Query, kind: str, args: tuple[int, ...]) -> None:
        origin = self.origin()
        text: str | bytes | None = None
        if self.answers is not None and kind == "trajectory":  # a pose/at answer (~1 KB) costs less than the trip
            try:
                text = self.answers.ask(kind, args, origin)
                self.stats["answered_elsewhere"] += 1
            except QueryProcessGone as exc:
                log.error("%s: queries are answered in the service's own process from now on", exc)
                self.answers = None
        if text is None:
            text = answer_text(self.history, kind, args, origin, self.lock)
        query.reply(query.key_expr, text, encoding=JSON)

    def _refuse_waiting(self, why: str) -> None:
        while True:
            try:
                _, query, _, _ = self._queries.get_nowait()
            except queue.Empty:
                return
            self._error(query, why)
