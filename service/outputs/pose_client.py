"""The mapper's side of the Zenoh interface: live poses, the pose at a time, a trajectory window.

A LIDAR scan takes about 100 ms and every return has its own time. Ask once for the trajectory
over the scan (:meth:`PoseClient.trajectory`) and interpolate locally for each return
(:meth:`~vtolpose.estimator.pose_history.PoseWindow.interpolate`): one round trip per scan instead of one
per return. :meth:`PoseClient.pose_at` answers a single time. Times are the estimator's sample
clock in integer nanoseconds (``t_ns`` of the published poses). Each pose says its ``kind``:
``predicted`` (ahead of the fusion horizon), ``filtered``, or ``smoothed`` (once the service's
fixed lag has passed: it also used the measurements after its time).

    with PoseClient("vtolpose/vtol1", connect=["tcp/192.168.1.10:7447"]) as client:
        sub = client.subscribe(lambda pose: print(pose.t_ns, pose.p))
        pose = client.pose_at(t_ns)
        window = client.trajectory(t_first_ns, t_last_ns)
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
import zenoh

from vtolpose.estimator.pose_history import PoseWindow
from vtolpose.service.outputs.zenoh_session import ZenohSettings

Origin = tuple[float, float, float] | None


class PoseUnavailable(LookupError):
    """The service answered with an error (e.g. the time is outside its history)."""


@dataclass(frozen=True, slots=True)
class Pose:
    """One pose: NED position/velocity [m, m/s], body→NED quaternion (w first), body rate [rad/s]."""

    t_ns: int
    p: np.ndarray
    q: np.ndarray
    v: np.ndarray
    w: np.ndarray
    cov: np.ndarray  # 6 × 6 over [δp, δθ] (attitude error in the NED frame)
    origin: Origin
    fused: bool
    status: str | None = None  # publications only: ok | poor | heading_weak | heading_unaligned | no_position
    seq: int | None = None  # publications only
    kind: str = "filtered"  # predicted | filtered | smoothed (see README, "Which pose to use")

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> "Pose":
        origin = doc.get("origin")

        def arr(key: str, shape: tuple) -> np.ndarray:
            return np.array([np.nan if x is None else x for x in np.ravel(doc[key])], dtype=float).reshape(shape)

        return cls(
            int(doc["t_ns"]), arr("p", (3,)), arr("q", (4,)), arr("v", (3,)), arr("w", (3,)), arr("cov", (6, 6)),
            None if origin is None else (origin["lat"], origin["lon"], origin["alt"]),
            bool(doc.get("fused", False)), doc.get("status"), doc.get("seq"),
            doc.get("kind") or ("filtered" if doc.get("fused", False) else "predicted"),
        )


def _decode(reply: zenoh.Reply) -> dict[str, Any]:
    if reply.ok is not None:
        return json.loads(reply.ok.payload.to_string())
    try:
        message = json.loads(reply.err.payload.to_string()).get("error", "error")
    except (ValueError, AttributeError):
        message = reply.err.payload.to_string()
    raise PoseUnavailable(message)


class PoseClient:
    """A Zenoh session talking to one vtolpose service (key prefix ``prefix``)."""

    def __init__(
        self,
        prefix: str = "vtolpose/vtol1",
        connect: Sequence[str] = (),
        listen: Sequence[str] = (),
        mode: str = "client",
        multicast_scouting: bool = False,
        timeout_s: float = 2.0,
        settings: ZenohSettings | None = None,
    ) -> None:
        self.prefix = prefix.rstrip("/")
        self.timeout_s = timeout_s
        settings = settings or ZenohSettings(mode, list(listen), list(connect), multicast_scouting)
        self.session = zenoh.open(settings.to_zenoh())
        self._subscribers: list[zenoh.Subscriber] = []

    def __enter__(self) -> "PoseClient":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        for sub in self._subscribers:
            sub.undeclare()
        self._subscribers = []
        self.session.close()

    def subscribe(self, callback: Callable[[Pose], None]) -> zenoh.Subscriber:
        """Call ``callback(pose)`` for every published pose (on a Zenoh thread)."""
        sub = self.session.declare_subscriber(
            f"{self.prefix}/pose", lambda sample: callback(Pose.from_json(json.loads(sample.payload.to_string())))
        )
        self._subscribers.append(sub)
        return sub

    def _query(self, selector: str) -> dict[str, Any]:
        replies = self.session.get(selector, timeout=self.timeout_s)
        for reply in replies:
            return _decode(reply)
        raise TimeoutError(f"no answer to {selector} within {self.timeout_s} s (is the service running and reachable?)")

    def pose_at(self, t_ns: int) -> Pose:
        """The pose interpolated at ``t_ns``; PoseUnavailable if the service's history does not cover it."""
        return Pose.from_json(self._query(f"{self.prefix}/pose/at?t_ns={int(t_ns)}"))

    def trajectory(self, t0_ns: int, t1_ns: int) -> PoseWindow:
        """The poses the service holds in ``[t0_ns, t1_ns]`` and the nearest one beyond each end, so that
        ``.interpolate(t_ns)`` answers any time in the window (a LIDAR scan's returns, for instance)."""
        doc = self._query(f"{self.prefix}/trajectory?from={int(t0_ns)};to={int(t1_ns)}")
        n = len(doc["t_ns"])

        def arr(key: str, cols: int) -> np.ndarray:
            return np.array([[np.nan if x is None else x for x in row] for row in doc[key]], dtype=float).reshape(n, cols)

        kind = doc.get("kind")
        return PoseWindow(np.array(doc["t_ns"], dtype=np.int64), arr("p", 3), arr("q", 4), arr("v", 3), arr("w", 3),
                          np.array(doc["fused"], dtype=bool), None if kind is None else np.array(kind, dtype=str),
                          arr("cov", 36).reshape(n, 6, 6) if "cov" in doc else None)
