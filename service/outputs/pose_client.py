"""The mapper's side of the Zenoh interface: live poses, the pose at a time, a trajectory window.

A LIDAR scan takes about 100 ms and every return has its own time. Ask once for the trajectory
over the scan (:meth:`PoseClient.trajectory`) and interpolate locally for each return
(:meth:`~vtolpose.estimator.pose_history.PoseWindow.interpolate`): one round trip per scan instead of one
per return. :meth:`PoseClient.pose_at` answers a single time. Times are the estimator's sample
clock in integer nanoseconds (``t_ns`` of the published poses). Each pose says its ``kind``:
``predicted`` (ahead of the fusion horizon), ``filtered``, or ``smoothed`` (once the service's
fixed lag has passed: it also used the measurements after its time).

    with PoseClient("vtolpose/vtol1", connect=["tcp/192.168.1.10:7448"]) as client:
        sub = client.subscribe(lambda pose: print(pose.t_ns, pose.p))
        pose = client.pose_at(t_ns)
        window = client.trajectory(t_first_ns, t_last_ns)

Only the vehicle's own session is believed. The service declares the liveliness token
``<prefix>/service/<its Zenoh id>``; the client takes that id as the service's (or the one given
as ``service_id``) and ignores answers whose replier and poses whose source is another session,
counting them in :attr:`PoseClient.ignored`. Two sessions claiming the prefix are refused until
``service_id`` says which is the vehicle. The ids are those Zenoh reports and a hostile Zenoh
implementation could claim another's; against that, the service's access control stops others
from publishing or answering under its prefix through it, and TLS with certificates keeps them
off the network (docs/zenoh.md).
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
import zenoh

from vtolpose.estimator import PoseWindow
from vtolpose.service.outputs.zenoh_session import ZenohSettings

Origin = tuple[float, float, float] | None


class PoseUnavailable(LookupError):
    """The service answered with an error (e.g. the time is outside its history), or it cannot be told apart
    from another session claiming its prefix."""


class ServiceUnreachable(ConnectionError):
    """The Zenoh session could not be opened (nothing listens at the endpoints, TLS refused, …)."""


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


def _error_text(reply: zenoh.Reply) -> str:
    try:
        return json.loads(reply.err.payload.to_string()).get("error", "error")
    except (ValueError, AttributeError):
        return reply.err.payload.to_string()


class PoseClient:
    """A Zenoh session talking to one vtolpose service (key prefix ``prefix``); see the module docstring
    for how it knows the service's answers and poses from anyone else's."""

    def __init__(
        self,
        prefix: str = "vtolpose/vtol1",
        connect: Sequence[str] = (),
        listen: Sequence[str] = (),
        mode: str = "client",
        multicast_scouting: bool = False,
        timeout_s: float = 2.0,
        settings: ZenohSettings | None = None,
        service_id: str | None = None,
    ) -> None:
        self.prefix = prefix.rstrip("/")
        self.timeout_s = timeout_s
        self.settings = settings or ZenohSettings(mode, list(listen), list(connect), multicast_scouting)
        try:
            self.session = zenoh.open(self.settings.to_zenoh())
        except zenoh.ZError as exc:
            raise ServiceUnreachable(
                f"cannot open a Zenoh session ({self.settings.endpoints_text()}): {str(exc).split(' at ')[0]}. Is "
                "`vtolpose run ... --zenoh` running, and listening on that endpoint? It logs where it listens "
                "(outputs.zenoh.listen, default tcp/127.0.0.1:7448)") from None
        self.pinned_service_id = service_id
        self.ignored = {"replies": 0, "samples": 0}  # from sessions that are not the service
        self._services: set[str] = set()
        self._services_changed = threading.Condition()
        self._subscribers: list[Any] = []
        self._tokens = self.session.liveliness().declare_subscriber(
            f"{self.prefix}/service/*", self._on_token, history=True)

    def __enter__(self) -> "PoseClient":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        for sub in [*self._subscribers, self._tokens]:
            try:
                sub.undeclare()
            except zenoh.ZError:  # already gone with its session
                pass
        self._subscribers = []
        self.session.close()

    # ------------------------------------------------------------------ the service's identity
    def _on_token(self, sample: zenoh.Sample) -> None:
        zid = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._services_changed:
            if sample.kind == zenoh.SampleKind.PUT:
                self._services.add(zid)
            else:
                self._services.discard(zid)
            self._services_changed.notify_all()

    def _trusted(self) -> str | None:
        """The service's Zenoh id now: the pinned one, else the only session claiming the prefix."""
        if self.pinned_service_id is not None:
            return self.pinned_service_id
        with self._services_changed:
            return next(iter(self._services)) if len(self._services) == 1 else None

    def service_id(self, wait_s: float | None = None) -> str:
        """The Zenoh id of the session whose answers are believed, waiting up to ``wait_s`` for it to appear.

        PoseUnavailable when several sessions claim the prefix (pass ``service_id`` to choose),
        TimeoutError when none does.
        """
        if self.pinned_service_id is not None:
            return self.pinned_service_id
        deadline = time.monotonic() + (self.timeout_s if wait_s is None else wait_s)
        with self._services_changed:
            while True:
                if len(self._services) == 1:
                    return next(iter(self._services))
                if len(self._services) > 1:
                    raise PoseUnavailable(
                        f"{len(self._services)} Zenoh sessions claim to be the vtolpose service under {self.prefix}/ "
                        f"({', '.join(sorted(self._services))}): none is believed; pass service_id= with the vehicle's "
                        "(it logs it at start)")
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"no vtolpose service under {self.prefix}/ ({self.settings.endpoints_text()}): "
                                       "is it running with --zenoh, under this prefix?")
                self._services_changed.wait(remaining)

    # ------------------------------------------------------------------------- subscriptions
    def _from_service(self, callback: Callable[[Any], None], parse: Callable[[dict], Any]) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            info, trusted = sample.source_info, self._trusted()
            if info is None or trusted is None or str(info.source_id.zid) != trusted:
                self.ignored["samples"] += 1
                return
            callback(parse(json.loads(sample.payload.to_string())))

        return on_sample

    def subscribe(self, callback: Callable[[Pose], None]) -> zenoh.Subscriber:
        """Call ``callback(pose)`` for every pose the service publishes (on a Zenoh thread)."""
        sub = self.session.declare_subscriber(f"{self.prefix}/pose", self._from_service(callback, Pose.from_json))
        self._subscribers.append(sub)
        return sub

    def subscribe_status(self, callback: Callable[[dict], None]) -> zenoh.Subscriber:
        """Call ``callback(document)`` for the service's status document (once a second, on a Zenoh thread)."""
        sub = self.session.declare_subscriber(f"{self.prefix}/status", self._from_service(callback, lambda doc: doc))
        self._subscribers.append(sub)
        return sub

    # ------------------------------------------------------------------------------- queries
    def _query(self, selector: str) -> dict[str, Any]:
        """The service's answer to ``selector``; answers from any other session are ignored (and counted).

        Every queryable is asked and no answer is merged with another, so that the service's own
        answer always arrives, however many others there are.
        """
        service = self.service_id()
        deadline = time.monotonic() + self.timeout_s
        pause_s = 0.005
        while True:
            replies = self.session.get(selector, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
                                       timeout=max(deadline - time.monotonic(), 0.01))
            for reply in replies:
                replier = reply.replier_id
                if replier is None or str(replier.zid) != service:
                    self.ignored["replies"] += 1
                    continue
                if reply.ok is None:
                    raise PoseUnavailable(_error_text(reply))
                return json.loads(reply.ok.payload.to_string())
            # Ended early without the service's answer: its per-client rate limit dropped the query
            # (outputs.zenoh.max_queries_per_s); ask again a little later, until the timeout.
            remaining = deadline - time.monotonic()
            if remaining <= pause_s:
                raise TimeoutError(f"no answer to {selector[:120]} from the service within {self.timeout_s} s "
                                   "(is it still running and reachable?)")
            time.sleep(pause_s)
            pause_s = min(2 * pause_s, 0.1)

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
