"""Zenoh outputs for the LIDAR mapper and anyone else (INTERFACES.md, "Out: Zenoh").

``<prefix>/pose`` carries every estimate, ``<prefix>/status`` a status document once a second;
the queryables ``<prefix>/pose/at?t_ns=…`` and ``<prefix>/trajectory?from=…;to=…`` answer from
the bounded pose history, each pose saying its ``kind`` (predicted, filtered, or smoothed once
the fixed lag has passed). Queries are served on Zenoh's own threads, so the history is read
under a lock the runtime also takes when it appends; an unanswerable query (time outside the
history, a malformed parameter) gets an error reply, never silence.
"""

from __future__ import annotations

import asyncio
import json
import logging
import threading
from typing import Any, Callable

import numpy as np
import zenoh

from vtolpose.estimator.fusion import OutputPose
from vtolpose.estimator.pose_history import OutsideHistory, PoseHistory
from vtolpose.service.outputs.zenoh_session import ZenohSettings
from vtolpose.service.runtime.status import heading_weak, pose_quality

log = logging.getLogger(__name__)

JSON = zenoh.Encoding.APPLICATION_JSON
Origin = tuple[float, float, float] | None


def pose_status(pose: OutputPose, quality: int) -> str:
    if not pose.position_initialized:
        return "no_position"
    if not pose.heading_aligned:
        return "heading_unaligned"
    if heading_weak(pose):
        return "heading_weak"
    return "ok" if quality > 0 else "poor"


def _floats(values: np.ndarray) -> list:
    """A plain list for JSON; non-finite numbers become null (JSON has no NaN)."""
    finite = np.isfinite(values)
    if finite.all():
        return values.tolist()
    return np.where(finite, values, None).tolist()


def _origin_json(origin: Origin) -> dict | None:
    return None if origin is None else {"lat": origin[0], "lon": origin[1], "alt": origin[2]}


def pose_message(pose: OutputPose, seq: int, origin: Origin) -> dict[str, Any]:
    """The ``<prefix>/pose`` document (INTERFACES.md), plus ``fused``, ``kind`` and ``quality``."""
    quality = pose_quality(pose)
    return {
        "t_ns": pose.t_ns, "frame": "NED", "origin": _origin_json(origin),
        "p": _floats(pose.p), "q": _floats(pose.q), "v": _floats(pose.v), "w": _floats(pose.omega_b),
        "cov": _floats(pose.pose_cov.reshape(36)), "status": pose_status(pose, quality),
        "seq": seq, "fused": pose.fused, "kind": "filtered" if pose.fused else "predicted", "quality": quality,
    }


class ZenohOutput:
    """Publishers and queryables on one Zenoh session."""

    name = "zenoh"

    def __init__(
        self,
        settings: ZenohSettings,
        prefix: str,
        history: PoseHistory,
        lock: threading.Lock,
        origin: Callable[[], Origin] = lambda: None,
    ) -> None:
        self.settings = settings
        self.prefix = prefix
        self.history = history
        self.lock = lock
        self.origin = origin
        self.session: zenoh.Session | None = None
        self._entities: list[Any] = []
        self._seq = 0
        self.stats = {"poses_published": 0, "queries": 0, "query_errors": 0}

    def open(self) -> None:
        self.session = s = zenoh.open(self.settings.to_zenoh())
        drop = zenoh.CongestionControl.DROP  # a slow subscriber must never stall the estimator
        self._pose_pub = s.declare_publisher(f"{self.prefix}/pose", encoding=JSON, congestion_control=drop, express=True)
        self._status_pub = s.declare_publisher(f"{self.prefix}/status", encoding=JSON, congestion_control=drop)
        self._entities = [
            self._pose_pub, self._status_pub,
            s.declare_queryable(f"{self.prefix}/pose/at", self._on_pose_at),
            s.declare_queryable(f"{self.prefix}/trajectory", self._on_trajectory),
        ]
        log.info("Zenoh session %s (%s): publishing under %s/", s.zid(), self.settings.mode, self.prefix)

    def close(self) -> None:
        for entity in self._entities:
            try:
                entity.undeclare()
            except zenoh.ZError as exc:  # the session is closing anyway; undeclare the rest
                log.debug("Zenoh undeclare on close: %s", exc)
        self._entities = []
        if self.session is not None:
            self.session.close()
            self.session = None

    # --------------------------------------------------------------------- publications
    def publish(self, pose: OutputPose) -> None:
        if self.session is None:
            return
        self._seq += 1
        self._pose_pub.put(json.dumps(pose_message(pose, self._seq, self.origin())))
        self.stats["poses_published"] += 1

    def publish_status(self, status: dict[str, Any]) -> None:
        if self.session is not None:
            self._status_pub.put(json.dumps(status))

    async def serve(self, stop: asyncio.Event) -> None:
        await stop.wait()  # everything happens in callbacks

    # ------------------------------------------------------------------------- queries
    def _error(self, query: zenoh.Query, message: str) -> None:
        self.stats["query_errors"] += 1
        query.reply_err(json.dumps({"error": message}), encoding=JSON)

    @staticmethod
    def _int_parameter(query: zenoh.Query, name: str) -> int:
        text = query.parameters.get(name)
        if text is None:
            raise ValueError(f"missing parameter {name}=<t_ns> (integer nanoseconds)")
        try:
            return int(text)
        except ValueError:
            raise ValueError(f"parameter {name}={text!r} is not an integer nanosecond time") from None

    def _on_pose_at(self, query: zenoh.Query) -> None:
        self.stats["queries"] += 1
        try:
            t_ns = self._int_parameter(query, "t_ns")
            with self.lock:
                pose = self.history.at(t_ns)
        except (ValueError, OutsideHistory) as exc:
            self._error(query, str(exc))
            return
        doc = {
            "t_ns": pose.t_ns, "frame": "NED", "origin": _origin_json(self.origin()),
            "p": _floats(pose.p), "q": _floats(pose.q), "v": _floats(pose.v), "w": _floats(pose.w),
            "cov": _floats(pose.cov.reshape(36)), "fused": pose.fused, "kind": pose.kind,
        }
        query.reply(query.key_expr, json.dumps(doc), encoding=JSON)

    def _on_trajectory(self, query: zenoh.Query) -> None:
        self.stats["queries"] += 1
        try:
            t0, t1 = self._int_parameter(query, "from"), self._int_parameter(query, "to")
            with self.lock:
                window = self.history.window(t0, t1)
        except (ValueError, OutsideHistory) as exc:
            self._error(query, str(exc))
            return
        doc = {
            "frame": "NED", "origin": _origin_json(self.origin()), "t_ns": window.t_ns.tolist(),
            "p": _floats(window.p), "q": _floats(window.q), "v": _floats(window.v), "w": _floats(window.w),
            "fused": window.fused.tolist(), "kind": window.kind.tolist(), "cov": _floats(window.cov.reshape(-1, 36)),
        }
        query.reply(query.key_expr, json.dumps(doc), encoding=JSON)
