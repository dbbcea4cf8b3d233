"""The autopilot's GPS over MAVLink: ``GPS_RAW_INT`` → local-NED fixes.

Only the raw receiver message is used: ``GLOBAL_POSITION_INT`` is the autopilot's own fused
estimate, and feeding it back would fuse the flight controller's errors as if they were
independent measurements. Sigmas come from the receiver's accuracy fields (``h_acc``/``v_acc``,
MAVLink 2 extensions) when set, else ``eph``/``epv`` (DOP × 100) × UERE. Height is the
ellipsoidal ``alt_ellipsoid`` when given, else MSL ``alt``. Fixes below 3-D, repeats of the same
receiver time, messages without any accuracy figure, and positions off the globe (latitude beyond
±90°, longitude beyond ±180°: a corrupted or uninitialised message) are counted and skipped.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any, Callable, Mapping

from vtolpose.drivers.gps.common import GpsReading, LocalNed, dop_sigmas, horizontal_per_axis
from vtolpose.drivers.links.mavlink_wire import ensure_mavlink2, mavutil
from vtolpose.estimator.core.measurements import GpsFix

__all__ = ["GPS_FIX_TYPE_3D", "MavlinkGps", "MavlinkGpsConfig"]

log = logging.getLogger(__name__)

GPS_FIX_TYPE_3D = 3
UNKNOWN_DOP = 65535


@dataclass(slots=True)
class MavlinkGpsConfig:
    url: str                                  # pymavlink connection string, e.g. udpin:0.0.0.0:14550
    uere_m: float = 4.0
    origin: tuple[float, float, float] | None = None
    system_id: int | None = None              # only this vehicle's messages (None: any)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], url: str | None = None) -> "MavlinkGpsConfig":
        origin = cfg["sensors.gps.origin"]
        return cls(url or cfg["sensors.gps.mavlink_url"], cfg["sensors.gps.uere_m"],
                   None if origin is None else tuple(origin), cfg.get("vehicle.system_id"))


class MavlinkGps:
    def __init__(self, config: MavlinkGpsConfig, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.config = config
        self._clock = clock
        self.local = LocalNed(config.origin)
        self.counts: Counter[str] = Counter()
        self.status = "closed"
        self._conn: Any = None
        self._last_time_usec: int | None = None

    def open(self) -> None:
        """Open the MAVLink endpoint (a UDP/TCP socket or serial port); raises OSError on failure."""
        ensure_mavlink2()
        self._conn = mavutil.mavlink_connection(self.config.url, autoreconnect=True)
        self.status = "listening"

    def close(self) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            except OSError as exc:  # the link is gone already; closing is all that was asked
                log.debug("MAVLink GPS link close: %s", exc)
        self._conn = None
        self.status = "closed"

    def __enter__(self) -> "MavlinkGps":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def read(self, timeout_s: float = 0.1) -> list[GpsReading]:
        """``GPS_RAW_INT`` fixes received within ``timeout_s``; never raises for I/O."""
        out: list[GpsReading] = []
        if self._conn is None:
            time.sleep(timeout_s)
            return out
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            try:
                msg = self._conn.recv_match(type="GPS_RAW_INT", blocking=left > 0, timeout=max(left, 0.0))
            except OSError as exc:
                self.counts["link_errors"] += 1
                self.status = f"link error: {exc}"
                return out
            if msg is None:
                return out
            reading = self.convert(msg, self._clock())
            if reading is not None:
                out.append(reading)
            if left <= 0:
                return out

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
