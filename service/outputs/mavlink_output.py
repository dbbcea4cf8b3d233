"""MAVLink 2 to the flight controller and ground stations: ODOMETRY, HEARTBEAT, STATUSTEXT, TIMESYNC answers.

One output, several endpoints (``outputs.mavlink.url`` and ``outputs.mavlink.endpoints``, see
config/mavlink_settings.py). Each endpoint has its own transport, signing key, ODOMETRY rate, counters and
failure book: an endpoint that fails is counted and skipped, the others go on. ODOMETRY fields follow
the autopilot's profile (:mod:`.mavlink_odometry`); ground stations get the generic fields. Only the
flight controller's link (``url``) feeds the estimator (``handlers``, e.g. the autopilot's GPS).

Incoming messages are read in slices of bounded work, on every link as soon as the loop reports its
descriptor readable: no request waits for a timer, so a TIMESYNC round trip splits evenly both ways
(a serial or TCP link's descriptor is followed through reconnections; such a link is opened and its
unsent bytes flushed every ``STREAM_SERVICE_S``). A slice stops after ``READ_BUDGET_S``; a link
whose slice ran out with data still waiting is left alone for ``READ_COOLDOWN_S``; the frames it had
read and not handled are handled first in the next slice (at most ``MAX_HELD_FRAMES``, one read
batch's), before the link is read again. So no input rate holds the estimator's loop longer than one
slice (a fraction of an IMU period), a flood takes at most a fixed share of it, and what it crowds
out waits in the kernel (a TCP sender is slowed) or is dropped there, not queued here.

TIMESYNC: a request (``tc1 = 0``) is answered at once with ``tc1`` = now on the clock ``time_usec`` is
in (:class:`SensorClock`: live, the host's monotonic clock the IMU is stamped on; a paced replay, the
replay's clock). PX4 asks first and, once its filter converges, maps ``time_usec`` onto its own clock
exactly. Without the clock itself, the answer follows the poses and lags by their age; until a first
pose there is then no clock and requests are counted, not answered. The age of each pose sent (IMU
stamp to send) is measured and reported with the delay parameter it suggests (``link_stats``).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import Counter, deque
from typing import Any, Callable, Sequence

from vtolpose.config.mavlink_settings import EndpointSpec, mavlink_endpoints
from vtolpose.config.sections import MavlinkSection
from vtolpose.drivers.links.mavlink_frames import Inbound
from vtolpose.drivers.links.mavlink_outbound import send_v2
from vtolpose.drivers.links.mavlink_signing import SigningKeyError, read_signing_key, signing_timestamp
from vtolpose.drivers.links.mavlink_transport import open_transport
from vtolpose.drivers.links.mavlink_wire import mavutil
from vtolpose.estimator import OutputPose
from vtolpose.service.outputs.mavlink_frame import PublishedFrame
from vtolpose.service.outputs.mavlink_odometry import (
    ODOMETRY_CRC_EXTRA, ODOMETRY_ID, PROFILES, Profile, euler_jacobian, odometry_covariances, odometry_fields,
    odometry_payload, upper_triangle,
)
from vtolpose.service.outputs.mavlink_status import StatusEvents, TextLimiter, statustext_chunks
from vtolpose.service.runtime.status import FailureBook, LatencyProbe, stopped_within

__all__ = ["COMPONENT_ID", "Endpoint", "MavlinkOutput", "SensorClock", "SigningKeyError", "OdometrySchedule",
           "euler_jacobian", "mavutil", "odometry_covariances", "odometry_fields", "read_signing_key", "upper_triangle"]

log = logging.getLogger(__name__)

mav = mavutil.mavlink
COMPONENT_ID = mav.MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY  # 197
READ_BUDGET_S = 0.0005
READ_COOLDOWN_S = 0.004
READ_BATCH = 4  # datagrams (or stream reads) between two looks at the clock
MAX_HELD_FRAMES = 1024  # frames of one batch kept for the next slice; more are dropped and counted
STREAM_SERVICE_S = 0.005  # a serial or TCP link (re)opened and its unsent bytes flushed this often
POSE_AGE_WINDOW = 3000  # ODOMETRY whose age the status figures cover (a minute at 50 Hz)
AUTOPILOT_NAMES = {mav.MAV_AUTOPILOT_PX4: "px4", mav.MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot"}


class SensorClock:
    """The sensor clock (``time_usec``'s) now.

    ``now``: that clock itself (live: the monotonic clock the IMU is stamped on; a paced replay: the
    replay's clock), the one TIMESYNC must answer on. Without it (or while it has no reading), the
    clock is followed from the poses as they are published: the pose's time plus the time since,
    which is late by the pose's age at publication. The age of each pose sent is measured against
    ``now`` (:meth:`age_ns`).
    """

    def __init__(self, clock: Callable[[], int] = time.monotonic_ns, now: Callable[[], int | None] | None = None) -> None:
        self._clock = clock
        self.now = now
        self._pose_t: int | None = None
        self._at = 0

    def follow(self, t_ns: int) -> None:
        self._pose_t, self._at = t_ns, self._clock()

    def now_ns(self) -> int | None:
        if self.now is not None:
            exact = self.now()
            if exact is not None:
                return exact
        return None if self._pose_t is None else self._pose_t + (self._clock() - self._at)

    def age_ns(self, t_ns: int) -> int | None:
        """How long ago ``t_ns`` was on the sensor clock; None without the clock itself."""
        exact = self.now() if self.now is not None else None
        return None if exact is None else exact - t_ns


class OdometrySchedule:
    """When to send: one every ``period_ns`` of sensor time on average (targets advance by the period, so
    rounding up to the next IMU sample does not lower the rate), never two closer than ``min_spacing_ns``."""

    def __init__(self, period_ns: int, min_spacing_ns: int = 0) -> None:
        self.period_ns, self.min_spacing_ns = period_ns, min_spacing_ns
        self._next: int | None = None
        self._last: int | None = None

    def due(self, t_ns: int) -> bool:
        if self._next is None or self._last is None or t_ns < self._last:
            self._next = t_ns  # the first pose, or time went back (a clock step): start again here
        elif t_ns < self._next or t_ns - self._last < self.min_spacing_ns:
            return False
        if t_ns - self._next >= self.period_ns:
            self._next = t_ns  # a hole in the poses: no burst to catch up
        self._next += self.period_ns
        self._last = t_ns
        return True


class Endpoint:
    """One MAVLink link: its transport, signing, ODOMETRY schedule, counters and failures."""

    def __init__(self, spec: EndpointSpec, key: bytes | None, profile: Profile, system_id: int, component_id: int,
                 max_peers: int = 4, peer_timeout_s: float = 10.0) -> None:
        self.spec, self.name = spec, spec.name
        self.profile = profile if spec.role == "autopilot" else PROFILES["generic"]
        self.inbound = Inbound(key, spec.require_signing)
        self.schedule = OdometrySchedule(int(round(1e9 / spec.rate_hz)), self.profile.min_spacing_ns)
        self._tx = mav.MAVLink(self, srcSystem=system_id, srcComponent=component_id)
        if key is not None:
            self._tx.signing.secret_key = key
            self._tx.signing.sign_outgoing = True
        self._max_peers, self._peer_timeout_s = max_peers, peer_timeout_s
        self.transport: Any = None
        self.stats: Counter[str] = Counter()
        self.failures = FailureBook()
        self.watched_fd: int | None = None  # the descriptor the loop reports readable for this link, if any
        self.resting = False  # a slice ran out of budget: not read for READ_COOLDOWN_S
        self.held: deque[tuple[bytes, Any]] = deque()  # frames read, not yet handled (a slice's budget ran out)
        self.peer_autopilot: str | None = None
        self.timesync_offset_ms: float | None = None
        self._reached = 0

    def open(self) -> None:
        self.transport = open_transport(self.spec.url, self._max_peers, self._peer_timeout_s)
        if self.transport.stream:
            self.transport.service()  # first attempt now; a missing device is retried with back-off

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()
            self.transport = None

    def write(self, buf: bytes) -> None:
        """pymavlink's encoder writes here."""
        self._reached = self.transport.send(buf)

    def send(self, msg: Any, counter: str) -> None:
        """Encode (sign) and send ``msg``; ``counter`` counts it when it reached at least one peer."""
        if self._before_send():
            self._tx.send(msg)
            if self._reached:
                self.stats[counter] += 1

    def send_packed(self, msg_id: int, crc_extra: int, payload: bytes, counter: str) -> None:
        """:meth:`send` for a payload already packed: framed here, bytes and link state as pymavlink's."""
        if self._before_send():
            send_v2(self._tx, msg_id, crc_extra, payload)
            if self._reached:
                self.stats[counter] += 1

    def _before_send(self) -> bool:
        if self.transport is None:
            return False
        if self._tx.signing.sign_outgoing:  # never behind the clock, even after a restart
            self._tx.signing.timestamp = max(self._tx.signing.timestamp, signing_timestamp())
        self._reached = 0
        return True

    def read(self, on_message: Callable[["Endpoint", Any], None], budget_s: float = READ_BUDGET_S) -> bool:
        """Handle waiting messages for at most ``budget_s``: first the frames an earlier slice read and had no
        budget left for, then what the link has. True when it stopped with some left (held, or maybe waiting)."""
        deadline = time.perf_counter() + budget_s
        held = self.held
        while True:
            if held:
                more = True  # the link is read again once they are handled
            else:
                frames, more = self.transport.receive(READ_BATCH)
                if len(frames) > MAX_HELD_FRAMES:  # only a batch of datagrams packed with frames gets here
                    self.stats["frames_dropped_over_budget"] += len(frames) - MAX_HELD_FRAMES
                    del frames[MAX_HELD_FRAMES:]
                held.extend(frames)
            while held:
                frame, peer = held.popleft()
                msg = self.inbound.accept(frame)
                if msg is not None:
                    self.transport.confirm_peer(peer)
                    try:
                        on_message(self, msg)
                    except Exception as exc:  # a handler's bug: counted, the link keeps reading
                        self.failures.record(f"MAVLink {self.name} handling {msg.get_type()}", exc)
                if time.perf_counter() >= deadline:
                    if held or more:
                        self.stats["read_budget_exhausted"] += 1
                        return True
                    return False
            if not more:
                return False

    def report(self) -> dict[str, Any]:
        doc: dict[str, Any] = {"url": self.spec.url, "role": self.spec.role, "rate_hz": self.spec.rate_hz}
        doc.update(self.stats)
        doc.update(self.inbound.counts)
        if self.transport is not None:
            doc.update(self.transport.counts)
            doc["peers"] = len(self.transport.peers)
        if self.inbound.check is not None:
            doc["signing_streams"] = self.inbound.check.streams
        if self.peer_autopilot is not None:
            doc["peer_autopilot"] = self.peer_autopilot
        if self.timesync_offset_ms is not None:
            doc["timesync_offset_ms"] = round(self.timesync_offset_ms, 3)
        if self.failures.parts:
            doc["failures"] = self.failures.report()
        return doc


class MavlinkOutput:
    """The MAVLink output: every endpoint, fed from the runtime's hot path and its status loop."""

    name = "mavlink"

    def __init__(self, endpoints: Sequence[Endpoint], autopilot: str = "generic", statustext_per_minute: int = 20,
                 clock: SensorClock | None = None) -> None:
        self.endpoints = list(endpoints)
        self.autopilot = autopilot
        primary = next((e for e in self.endpoints if e.spec.role == "autopilot"), None)
        self.url = primary.spec.url if primary is not None else None  # the link the estimator's inputs may come from
        self._primary = primary
        self.handlers: dict[str, Callable[[Any], None]] = {}
        self.clock = clock or SensorClock()
        self.events = StatusEvents()
        self.limiter = TextLimiter(statustext_per_minute) if statustext_per_minute > 0 else None
        self._chunk_id = 0
        self._active = False
        self._loop: asyncio.AbstractEventLoop | None = None
        # Per autopilot profile: the frame it is told, the steps it gets (PX4's FRD, ArduPilot's yaw).
        self.frames = {name: PublishedFrame(name) for name in dict.fromkeys(e.profile.name for e in self.endpoints)}
        self.pose_age = LatencyProbe(POSE_AGE_WINDOW)  # IMU stamp to ODOMETRY sent, on the sensor clock

    @classmethod
    def from_section(cls, mavlink: MavlinkSection, system_id: int, clock: SensorClock | None = None) -> "MavlinkOutput":
        """Endpoints from ``outputs.mavlink``, sending as ``vehicle.system_id``; ValueError naming the key of an
        unusable signing key."""
        profile = PROFILES[mavlink.autopilot]
        endpoints = []
        for spec in mavlink_endpoints(mavlink):
            key = None
            if spec.signing_key_file is not None:
                try:
                    key = read_signing_key(spec.signing_key_file)
                except SigningKeyError as exc:
                    raise ValueError(f"key '{spec.key}.signing_key_file': {exc}") from None
            endpoints.append(Endpoint(spec, key, profile, system_id, mavlink.component_id, mavlink.max_udp_peers,
                                      mavlink.udp_peer_timeout_s))
        return cls(endpoints, mavlink.autopilot, mavlink.statustext_per_minute, clock)

    # ------------------------------------------------------------------------------ lifetime
    def open(self) -> None:
        try:
            for endpoint in self.endpoints:
                try:
                    endpoint.open()
                except OSError as exc:
                    raise OSError(f"MAVLink endpoint {endpoint.name} ({endpoint.spec.url}): {exc}") from exc
                log.info("MAVLink endpoint %s open: %s, %s%s", endpoint.name, endpoint.spec.url, endpoint.spec.role,
                         ", signed" if endpoint.inbound.check is not None else "")
        except OSError:
            self.close()
            raise

    def close(self) -> None:
        for endpoint in self.endpoints:
            self._unwatch(endpoint)
            endpoint.close()

    # ------------------------------------------------------------------------------ outgoing
    def publish(self, pose: OutputPose) -> bool:
        """ODOMETRY to every endpoint whose schedule is due. True when at least one was sent.

        It runs for every IMU sample: each profile's payload is packed once, and framed per endpoint
        without pymavlink's message objects (:meth:`Endpoint.send_packed`)."""
        self.clock.follow(pose.t_ns)
        for frame in self.frames.values():
            frame.follow(pose)
        payloads: dict[str, tuple[bytes, int]] = {}
        sent = False
        for endpoint in self.endpoints:
            if endpoint.transport is None or not endpoint.schedule.due(pose.t_ns):
                continue
            try:
                profile = endpoint.profile
                if profile.name not in payloads:
                    shown, frame_id, resets = self.frames[profile.name].present(pose)
                    f = odometry_fields(shown, profile, frame_id, resets)
                    payloads[profile.name] = odometry_payload(f), f["quality"]
                payload, quality = payloads[profile.name]
                endpoint.send_packed(ODOMETRY_ID, ODOMETRY_CRC_EXTRA, payload, "odometry_sent")
                if not sent:
                    age = self.clock.age_ns(pose.t_ns)
                    if age is not None:
                        self.pose_age.add(age)
                sent = True
                if endpoint is self._primary:
                    self._active = quality > 0
            except Exception as exc:  # this endpoint only; the others still get their pose
                endpoint.failures.record(f"MAVLink {endpoint.name} ODOMETRY", exc)
        return sent

    def heartbeat(self) -> None:
        state = mav.MAV_STATE_ACTIVE if self._active else mav.MAV_STATE_STANDBY
        msg = mav.MAVLink_heartbeat_message(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0, state, 3)
        self._each(lambda e: e.send(msg, "heartbeats_sent"), "HEARTBEAT")

    def statustext(self, severity: int, text: str) -> None:
        """``text`` to every endpoint (and the log), chunked when longer than one message holds."""
        log.log(logging.WARNING if severity <= mav.MAV_SEVERITY_WARNING else logging.INFO, "STATUSTEXT: %s", text)
        self._chunk_id = self._chunk_id % 65535 + 1
        for data, chunk_id, seq in statustext_chunks(text, self._chunk_id):
            msg = mav.MAVLink_statustext_message(severity, data, chunk_id, seq)
            self._each(lambda e: e.send(msg, "statustext_sent"), "STATUSTEXT")

    def publish_status(self, status: dict[str, Any]) -> None:
        """Resets, stale sensors and the heading, as STATUSTEXT (rate-limited)."""
        changes = self.events.changes(status)
        if self.limiter is None or not changes:
            return
        for severity, text in self.limiter.admit(changes):
            self.statustext(severity, text)

    def _each(self, action: Callable[[Endpoint], None], what: str) -> None:
        for endpoint in self.endpoints:
            try:
                action(endpoint)
            except Exception as exc:
                endpoint.failures.record(f"MAVLink {endpoint.name} {what}", exc)

    # ------------------------------------------------------------------------------ incoming
    def _on_message(self, endpoint: Endpoint, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "TIMESYNC":
            self._timesync(endpoint, msg)
        elif kind == "HEARTBEAT" and endpoint.spec.role == "autopilot" and msg.autopilot in AUTOPILOT_NAMES:
            seen = AUTOPILOT_NAMES[msg.autopilot]
            if seen != endpoint.peer_autopilot:
                endpoint.peer_autopilot = seen
                if self.autopilot != "generic" and seen != self.autopilot:
                    log.warning("MAVLink %s: the flight controller says it is %s, but outputs.mavlink.autopilot is %s",
                                endpoint.name, seen, self.autopilot)
        if endpoint is self._primary:
            handler = self.handlers.get(kind)
            if handler is not None:
                handler(msg)

    def _timesync(self, endpoint: Endpoint, msg: Any) -> None:
        if msg.tc1 != 0:
            endpoint.stats["timesync_responses_ignored"] += 1  # we ask nobody: not ours
            return
        now = self.clock.now_ns()
        if now is None:
            endpoint.stats["timesync_unanswered_no_pose_yet"] += 1
            return
        endpoint.send(mav.MAVLink_timesync_message(now, msg.ts1), "timesync_answered")
        endpoint.timesync_offset_ms = (msg.ts1 - now) * 1e-6  # their clock minus ours, plus the one-way delay

    def poll(self, endpoint: Endpoint | None = None) -> None:
        """Read what waits on ``endpoint`` (every endpoint if None), one budgeted slice each."""
        for e in [endpoint] if endpoint is not None else self.endpoints:
            if e.transport is not None:
                e.read(self._on_message)

    def _watch(self, endpoint: Endpoint) -> None:
        """Have the loop report the link's descriptor as it is now: none while the link is closed or
        reopening, the new one after a reconnection (a UDP socket's never changes)."""
        loop = self._loop
        transport = endpoint.transport
        fd = transport.fileno() if transport is not None and loop is not None else None
        if fd == endpoint.watched_fd:
            return
        self._unwatch(endpoint)
        if fd is not None:
            loop.add_reader(fd, self._on_readable, endpoint)
            endpoint.watched_fd = fd

    def _unwatch(self, endpoint: Endpoint) -> None:
        if endpoint.watched_fd is not None and self._loop is not None:
            self._loop.remove_reader(endpoint.watched_fd)
        endpoint.watched_fd = None

    def _on_readable(self, endpoint: Endpoint) -> None:
        try:
            exhausted = endpoint.read(self._on_message)
        except Exception as exc:
            endpoint.failures.record(f"MAVLink {endpoint.name} reading", exc)
            exhausted = True
        if exhausted and self._loop is not None:
            self._unwatch(endpoint)  # rests for READ_COOLDOWN_S; the serve loop must not take it back before
            endpoint.resting = True
            self._loop.call_later(READ_COOLDOWN_S, self._resume, endpoint)
        else:
            self._watch(endpoint)  # the read may have lost the link (a stream's descriptor is then gone)

    def _resume(self, endpoint: Endpoint) -> None:
        endpoint.resting = False
        self._watch(endpoint)
        if endpoint.held and endpoint.watched_fd is not None:  # already read: no readiness will come for them
            self._on_readable(endpoint)

    def link_stats(self) -> dict[str, Any]:
        """Totals over the endpoints, and each endpoint's own report under ``endpoints``."""
        reports = {e.name: e.report() for e in self.endpoints}
        totals = {key: sum(r.get(key, 0) for r in reports.values())
                  for key in ("odometry_sent", "heartbeats_sent", "statustext_sent", "received", "bad_data")}
        doc = {**totals, "statustext_held_back": self.limiter.suppressed_total if self.limiter else 0,
               "frames": {name: frame.report() for name, frame in self.frames.items()}}
        if len(self.pose_age):
            p50, p99, pmax = self.pose_age.percentiles_ms(50, 99, 100)
            # The autopilot's delay parameter (VISO_DELAY_MS; EKF2_EV_DELAY where PX4 stamps on arrival):
            # the pose's usual age when it leaves, whole milliseconds up; the link's transfer time comes on top.
            doc["pose_age_ms"] = {"p50": round(p50, 3), "p99": round(p99, 3), "max": round(pmax, 3)}
            doc["delay_to_configure_ms"] = max(0, math.ceil(p50))
        doc["endpoints"] = reports
        return doc

    async def serve(self, stop: asyncio.Event) -> None:
        """HEARTBEAT every second; every link read when readable; serial and TCP links kept open."""
        loop = self._loop = asyncio.get_running_loop()
        for endpoint in self.endpoints:
            endpoint.resting = False  # a rest begun under an earlier loop ended with it
            if endpoint.transport is not None and endpoint.transport.stream:
                endpoint.transport.before_close = lambda e=endpoint: self._unwatch(e)  # while its descriptor is open
        streams = any(e.transport is not None and e.transport.stream for e in self.endpoints)
        tick = STREAM_SERVICE_S if streams else 0.1
        next_beat = loop.time()
        try:
            while not stop.is_set():
                if loop.time() >= next_beat:
                    next_beat = max(next_beat + 1.0, loop.time())
                    self.heartbeat()
                for endpoint in self.endpoints:
                    if endpoint.transport is None:
                        continue
                    try:
                        endpoint.transport.service()
                        if not endpoint.resting:
                            self._watch(endpoint)
                    except Exception as exc:  # a socket error or a bug: counted, the link keeps serving
                        endpoint.failures.record(f"MAVLink {endpoint.name}", exc)
                await stopped_within(stop, tick)
        finally:
            for endpoint in self.endpoints:
                self._unwatch(endpoint)
                if endpoint.transport is not None and endpoint.transport.stream:
                    endpoint.transport.before_close = None
            self._loop = None
