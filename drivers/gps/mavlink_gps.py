"""The autopilot's GPS over MAVLink: ``GPS_RAW_INT`` → local-NED fixes.

Only the raw receiver message is used: ``GLOBAL_POSITION_INT`` is the autopilot's own fused
estimate, and feeding it back would fuse the flight controller's errors as if they were
independent measurements. Sigmas come from the receiver's accuracy fields (``h_acc``/``v_acc``,
MAVLink 2 extensions) when set, else ``eph``/``epv`` (DOP × 100) × UERE. Height is the
ellipsoidal ``alt_ellipsoid`` when given, else MSL ``alt``. Fixes below 3-D, repeats of the same
receiver time, messages without any accuracy figure, and positions off the globe (latitude beyond
±90°, longitude beyond ±180°: a corrupted or uninitialised message) are counted and skipped.

The link is built from the MAVLink output's parts (:mod:`vtolpose.drivers.links`): a non-blocking
transport, and whole frames checked by :class:`~vtolpose.drivers.links.mavlink_frames.Inbound` (with a
key, a signature is verified before its stream's timestamp moves; with ``require_signing``, unsigned,
forged, replayed and unknown-id messages are refused and counted). Only the configured system's
messages are used; other known message ids are counted and skipped without being decoded.

The reader spends at most ``READ_BUDGET_S`` of its thread's CPU time in one go and at most
``MAX_CPU_SHARE`` of a core over time (a budget that refills at that rate; spent, the reader sleeps until
it is whole again), however the input is paced. Frames already read when the budget runs out wait
for the next slice (at most ``MAX_HELD_FRAMES``). What a flood crowds out is dropped, by the kernel or
here, and counted (``kernel_dropped_datagrams``, ``frames_dropped_over_budget``), never queued without
bound: a flood beyond the budget costs fixes (the GPS goes stale, and the status says so), never more
of the process's time than that share.
The driver never sends; a ``udpin`` link remembers at most ``MAX_PEERS`` senders of valid fixes (for
the report), however many addresses send.
"""

from __future__ import annotations

import logging
import math
import select
import time
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any, Callable

from vtolpose.config import ConfigError
from vtolpose.config.sections import GpsSection
from vtolpose.drivers.gps.common import GpsReading, LocalNed, dop_sigmas, horizontal_per_axis
from vtolpose.drivers.links.mavlink_frames import Inbound, frame_header
from vtolpose.drivers.links.mavlink_signing import SigningKeyError, read_signing_key
from vtolpose.drivers.links.mavlink_transport import open_transport
from vtolpose.drivers.links.mavlink_wire import ensure_mavlink2, mavutil
from vtolpose.estimator.core.measurements import GpsFix

__all__ = ["GPS_FIX_TYPE_3D", "MavlinkGps", "MavlinkGpsConfig", "mavutil"]

log = logging.getLogger(__name__)

mav = mavutil.mavlink
GPS_FIX_TYPE_3D = 3
UNKNOWN_DOP = 65535
GPS_RAW_INT_ID = mav.MAVLINK_MSG_ID_GPS_RAW_INT
READ_BUDGET_S = 0.001  # most CPU time the reader spends in one go
MAX_CPU_SHARE = 0.2  # ... and over time: its budget refills at this many CPU seconds per second
READ_BATCH = 4  # datagrams (or stream reads) taken at once
MAX_HELD_FRAMES = 1024  # frames read but not yet handled when a slice's budget ran out; more are dropped, counted
CONNECT_POLL_S = 0.05  # a serial port or TCP link not (yet) open: look again this often
MAX_PEERS = 4  # udpin senders of valid fixes remembered
PEER_TIMEOUT_S = 10.0
WORTH_A_WARNING = ("refused_", "kernel_dropped", "frames_dropped", "read_budget", "peers_refused")  # counters


@dataclass(slots=True)
class MavlinkGpsConfig:
    url: str                                  # udpin:HOST:PORT, tcp:HOST:PORT or /dev/ttyX[,BAUD]
    uere_m: float = 4.0
    origin: tuple[float, float, float] | None = None
    system_id: int | None = None              # only this vehicle's messages (None: any)
    signing_key: bytes | None = None          # 32 bytes: signed messages are checked with it
    require_signing: bool = False             # refuse every message not signed with the key

    @classmethod
    def from_section(cls, gps: GpsSection, system_id: int | None, url: str | None = None) -> "MavlinkGpsConfig":
        """From ``sensors.gps`` and ``vehicle.system_id``; ConfigError naming the key of an unusable signing key."""
        key = None
        if gps.signing_key_file is not None:
            try:
                key = read_signing_key(gps.signing_key_file)
            except SigningKeyError as exc:
                raise ConfigError(f"key 'sensors.gps.signing_key_file': {exc}") from None
        if gps.require_signing and key is None:
            raise ConfigError("key 'sensors.gps.require_signing': needs sensors.gps.signing_key_file")
        return cls(url or gps.mavlink_url, gps.uere_m, None if gps.origin is None else tuple(gps.origin), system_id, key,
                   gps.require_signing)


class MavlinkGps:
    def __init__(self, config: MavlinkGpsConfig, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.config = config
        self._clock = clock
        self.local = LocalNed(config.origin)
        self.counts: Counter[str] = Counter()  # the link's one book: conversion, frame checks and transport
        self.status = "closed"
        self.inbound = Inbound(config.signing_key, config.require_signing)
        self.inbound.counts = self.counts
        self._transport: Any = None
        self._cpu_left, self._refilled_at = READ_BUDGET_S, time.monotonic()  # the reader's CPU budget [s]
        self._held: deque[tuple[bytes, Any]] = deque()  # frames read but not yet handled (budget ran out)
        self._reported: set[str] = set()  # link counters already logged once
        self._last_time_usec: int | None = None

    def open(self) -> None:
        """Open the link (a UDP/TCP socket or serial port); OSError when a UDP port cannot be bound,
        ValueError for a malformed URL. A serial port or TCP peer that is not there yet is retried with back-off."""
        ensure_mavlink2()
        self._transport = open_transport(self.config.url, MAX_PEERS, PEER_TIMEOUT_S)
        self._transport.counts = self.counts
        if self._transport.stream:
            self._transport.service()
        self.status = "listening"

    def close(self) -> None:
        if self._transport is not None:
            self._transport.close()
        self._transport = None
        self._held.clear()
        self.status = "closed"

    def __enter__(self) -> "MavlinkGps":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def peers(self) -> list[Any]:
        """The senders of valid fixes remembered (a ``udpin`` link: at most ``MAX_PEERS``)."""
        return [] if self._transport is None else self._transport.peers

    def read(self, timeout_s: float = 0.1) -> list[GpsReading]:
        """Fixes of the first slice that gave any, waiting up to ``timeout_s``; never raises for I/O."""
        out: list[GpsReading] = []
        transport = self._transport
        if transport is None:
            time.sleep(timeout_s)
            return out
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                transport.service()  # (re)open a serial port or TCP link when its back-off allows
                if transport.stream and not transport.connected:
                    self.status = f"waiting for {self.config.url} ({transport.counts['open_failures']} failed opens)"
                now = time.monotonic()
                self._cpu_left = min(READ_BUDGET_S, self._cpu_left + (now - self._refilled_at) * MAX_CPU_SHARE)
                self._refilled_at = now
                if self._cpu_left <= 0.0:  # its share is spent: leave the time to others until the budget is whole
                    time.sleep(max(0.0, min((READ_BUDGET_S - self._cpu_left) / MAX_CPU_SHARE, deadline - now)))
                elif self._held or self._readable(transport, deadline - now):
                    self._cpu_left -= self._slice(transport, out, self._cpu_left)
            except (OSError, ValueError) as exc:  # a socket or port error; ValueError: a port closed under us
                self.counts["link_errors"] += 1
                self.status = f"link error: {exc}"
                time.sleep(max(0.0, min(CONNECT_POLL_S, deadline - time.monotonic())))
            if out or time.monotonic() >= deadline:
                self._log_new_refusals()
                return out

    @staticmethod
    def _readable(transport: Any, wait_s: float) -> bool:
        fd = transport.fileno()
        if fd is None:  # a stream link that is not open (yet)
            time.sleep(max(0.0, min(wait_s, CONNECT_POLL_S)))
            return False
        poller = select.poll()  # not select(): a daemon's descriptors may number past FD_SETSIZE
        poller.register(fd, select.POLLIN)
        return bool(poller.poll(max(0, math.ceil(wait_s * 1000))))

    def _slice(self, transport: Any, out: list[GpsReading], budget_s: float) -> float:
        """Handle waiting frames until ``budget_s`` of this thread's own CPU time is spent (time spent
        preempted, or waiting for the interpreter lock, is not work); the CPU time it took. Frames already
        read when the budget runs out are held for the next slice, at most ``MAX_HELD_FRAMES``."""
        start = time.thread_time()
        deadline = start + budget_s
        waiting = True  # the transport may have more
        while True:
            while self._held:
                frame, peer = self._held.popleft()
                reading = self._take(frame, peer)
                if reading is not None:
                    out.append(reading)
                if time.thread_time() >= deadline:
                    self.counts["read_budget_exhausted"] += 1
                    return time.thread_time() - start
            if not waiting:
                return time.thread_time() - start
            frames, waiting = transport.receive(READ_BATCH)
            room = MAX_HELD_FRAMES - len(self._held)
            if len(frames) > room:
                self.counts["frames_dropped_over_budget"] += len(frames) - room
                del frames[room:]
            self._held.extend(frames)

    def _take(self, frame: bytes, peer: Any) -> GpsReading | None:
        msg_id, _, _, signed = frame_header(frame)
        if msg_id != GPS_RAW_INT_ID and msg_id in mav.mavlink_map and (signed or not self.inbound.require_signing):
            self.counts["other_messages"] += 1  # not decoded: nothing in it is used here
            return None
        msg = self.inbound.accept(frame)  # GPS_RAW_INT, or a frame to refuse (unsigned, unknown id)
        if msg is None:
            return None
        reading = self.convert(msg, self._clock())
        if self.config.system_id is None or msg.get_srcSystem() == self.config.system_id:
            self._transport.confirm_peer(peer)
        return reading

    def link_stats(self) -> dict[str, Any]:
        """The link's counters for the status document: ``received`` (frames that passed every check),
        ``refused`` (all ``refused_*``), ``unsigned`` (refused for it, or let through without signing
        required), the signing rule, and every counter by name."""
        counts = dict(self.counts)  # a copy: the reader thread goes on counting
        signing = "required" if self.inbound.require_signing else "checked" if self.inbound.check is not None else "off"
        return {"url": self.config.url, "status": self.status, "signing": signing,
                "received": counts.get("received", 0),
                "refused": sum(n for name, n in counts.items() if name.startswith("refused_")),
                "unsigned": counts.get("refused_unsigned", 0) + counts.get("unsigned_accepted", 0),
                "counters": counts}

    def _log_new_refusals(self) -> None:
        """The first time each kind of refusal or loss happens, say so; the counters keep the totals."""
        for name, count in list(self.counts.items()):
            if name not in self._reported and name.startswith(WORTH_A_WARNING):
                self._reported.add(name)
                log.warning("MAVLink GPS link %s: %s (%d so far; counted from now on)", self.config.url,
                            name.replace("_", " "), count)

    def convert(self, msg: Any, t_ns: int) -> GpsReading | None:
        if self.config.system_id is not None and msg.get_srcSystem() != self.config.system_id:
            self.counts["other_system"] += 1
            return None
        self.counts["messages"] += 1
        if msg.fix_type < GPS_FIX_TYPE_3D:
            self.counts["no_fix"] += 1
            return None
        if msg.time_usec and msg.time_usec == self._last_time_usec:
            self.counts["duplicate"] += 1
            return None
        self._last_time_usec = msg.time_usec
        h_acc, v_acc = getattr(msg, "h_acc", 0) or 0, getattr(msg, "v_acc", 0) or 0
        if h_acc > 0 and v_acc > 0:
            sigma_h, sigma_v, source = horizontal_per_axis(h_acc * 1e-3), v_acc * 1e-3, "accuracy"
        elif msg.eph != UNKNOWN_DOP and msg.eph > 0:
            vdop = None if msg.epv in (0, UNKNOWN_DOP) else msg.epv / 100.0
            (sigma_h, sigma_v), source = dop_sigmas(msg.eph / 100.0, vdop, self.config.uere_m), "DOP"
        else:
            self.counts["no_accuracy"] += 1
            return None
        lat, lon = msg.lat * 1e-7, msg.lon * 1e-7
        if abs(lat) > 90.0 or abs(lon) > 180.0:
            self.counts["implausible"] += 1
            return None
        alt = (getattr(msg, "alt_ellipsoid", 0) or msg.alt) * 1e-3
        self.counts["fixes"] += 1
        self.status = "receiving"
        p = self.local(lat, lon, alt)
        sats = None if msg.satellites_visible == 255 else int(msg.satellites_visible)
        hdop = None if msg.eph == UNKNOWN_DOP else msg.eph / 100.0
        return GpsReading(GpsFix(t_ns, p, sigma_h, sigma_v), lat, lon, alt, source, sats, hdop)
