"""NMEA 0183 GPS receiver over serial (pynmea2): GGA position, RMC validity, GSA/GST errors.

One fix per epoch, dated on the host clock when its GGA line arrived. Its sigmas come from GST
(the receiver's own 1-σ latitude/longitude/altitude errors) when the receiver sends GST — a
fix waits up to ``GST_WAIT_S`` (or until the next GGA) for its epoch's GST, unless the receiver
has shown it sends none — else from HDOP (and GSA's VDOP) × UERE. Bad checksums, cut-off lines, garbage and no-fix epochs are
counted and skipped; ``read()`` never raises for I/O and reopens a lost port with back-off.
The XOR checksum lets about one corrupted line in 256 through, so a sentence whose fields are
malformed or out of range (hemisphere letters, latitude beyond 90°, absurd heights or error
figures) is counted as ``implausible`` (``gst_implausible``) and skipped too.
"""

from __future__ import annotations

import logging
import math
import re
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any, Callable

import pynmea2

from vtolpose.config.sections import SensorsSection
from vtolpose.drivers.gps.common import GpsReading, LocalNed, dop_sigmas, horizontal_per_axis
from vtolpose.drivers.links.serial_link import LINK_ERRORS, Backoff, SerialLink
from vtolpose.estimator.core.measurements import GpsFix

__all__ = ["GST_WAIT_S", "NmeaConfig", "NmeaGps"]

log = logging.getLogger(__name__)

GST_WAIT_S = 0.3      # how long a fix waits for its epoch's GST before falling back to DOP
MAX_LINE = 200        # NMEA allows 82 characters; anything much longer is garbage
MAX_DOP = 100.0       # NMEA dilution fields hold at most 99.99
MAX_SIGMA_M = 1.0e5   # a GST error figure beyond 100 km is line noise, not a receiver estimate
MAX_HEIGHT_M = 1.0e5  # receivers stop reporting far below 100 km
_DEGREES_MINUTES = re.compile(r"(\d{1,3})([0-5]\d\.\d+)")  # (d)ddmm.mmmm, minutes below 60


@dataclass(slots=True)
class NmeaConfig:
    port: str
    baud: int = 9600
    uere_m: float = 4.0
    origin: tuple[float, float, float] | None = None
    silence_timeout_s: float = 3.0
    reconnect_min_s: float = 0.5
    reconnect_max_s: float = 10.0

    @classmethod
    def from_section(cls, sensors: SensorsSection, port: str | None = None, baud: int | None = None) -> "NmeaConfig":
        """From ``sensors.gps`` and the drivers' shared back-off (``sensors.reconnect_*``), with optional
        command-line overrides."""
        gps = sensors.gps
        return cls(port or gps.port, int(baud or gps.baud), gps.uere_m, None if gps.origin is None else tuple(gps.origin),
                   gps.silence_timeout_s, sensors.reconnect_min_s, sensors.reconnect_max_s)


@dataclass(slots=True)
class _Epoch:
    t_ns: int
    utc: Any
    lat: float
    lon: float
    alt: float
    satellites: int | None
    hdop: float | None


def _number(text: str | None) -> float | None:
    try:
        value = float(text) if text not in (None, "") else None
    except ValueError:
        return None
    return value if value is not None and math.isfinite(value) else None


def _dop(text: str | None) -> float | None:
    value = _number(text)
    return value if value is not None and 0.0 < value < MAX_DOP else None


def _degrees(text: Any, hemisphere: Any, signs: tuple[str, str], limit: float) -> float | None:
    """Signed degrees from ``(d)ddmm.mmmm`` and its hemisphere letter (``signs``: positive, negative);
    None unless both are well-formed and the angle is at most ``limit``."""
    match = _DEGREES_MINUTES.fullmatch(text) if isinstance(text, str) else None
    if match is None or hemisphere not in signs:
        return None
    degrees = int(match[1]) + float(match[2]) / 60.0
    if degrees > limit:
        return None
    return -degrees if hemisphere == signs[1] else degrees


class NmeaGps:
    """Reads NMEA sentences from a serial port and turns complete epochs into GPS fixes."""

    def __init__(self, config: NmeaConfig, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.config = config
        self._clock = clock
        self._link = SerialLink(config.port, config.baud, clock)
        self._backoff = Backoff(config.reconnect_min_s, config.reconnect_max_s)
        self.local = LocalNed(config.origin)
        self.counts: Counter[str] = Counter()     # lines, fixes, and every reason a line or epoch was skipped
        self.sentence_types: Counter[str] = Counter()
        self.status = "closed"
        self._line = bytearray()
        self._pending: _Epoch | None = None
        self._gst: tuple[Any, float, float, float] | None = None  # (utc, sigma_lat, sigma_lon, sigma_alt)
        self._vdop: float | None = None
        self._rmc_void_utc: Any = None
        self._expect_gst = True   # until an epoch passes without one: then fixes go out at once
        self._gst_seen = False
        self._last_line_ns = 0
        self._closed = False

    # -- connection ---------------------------------------------------------------------------
    def open(self) -> None:
        """Open the port now (raises OSError/SerialException naming it); ``read`` reopens later."""
        self._closed = False
        self._link.open()
        self._connected()

    def _connected(self) -> None:
        self._line.clear()
        self._last_line_ns = self._clock()
        self._backoff.succeeded()
        self.counts["connects"] += 1
        self.status = "receiving"

    def _drop(self, reason: str) -> None:
        self._link.close()
        self.status = f"reconnecting: {reason}"
        log.warning("GPS on %s: %s; reconnecting", self.config.port, reason)

    def close(self) -> None:
        self._closed = True
        self._link.close()
        self.status = "closed"

    def __enter__(self) -> "NmeaGps":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- data ---------------------------------------------------------------------------------
    def read(self, timeout_s: float = 0.1) -> list[GpsReading]:
        """Fixes completed within ``timeout_s`` (possibly none); never raises for I/O."""
        out: list[GpsReading] = []
        if self._closed:
            return out
        if not self._link.is_open:
            if not self._backoff.ready():
                time.sleep(min(timeout_s, self._backoff.wait_s()))
                return out
            try:
                self._link.open()
                self._connected()
            except LINK_ERRORS as exc:
                self._backoff.failed()
                self.status = f"reconnecting: {exc}"
            return out
        try:
            data, t_ns = self._link.read(timeout_s)
        except Exception as exc:
            if self._closed:
                return out  # closed by another thread while this one was reading
            if not isinstance(exc, LINK_ERRORS):
                raise
            self.counts["link_errors"] += 1
            self._drop(f"link error: {exc}")
            return out
        for i, byte in enumerate(data):
            if byte == 0x0A:  # a line ends: date it by its newline byte
                self._on_line(bytes(self._line), t_ns - (len(data) - 1 - i) * self._link.byte_time_ns, out)
                self._line.clear()
            elif len(self._line) < MAX_LINE:
                self._line.append(byte)
            else:
                self.counts["garbled"] += 1
                self._line.clear()
        now = self._clock()
        if self._pending is not None and now - self._pending.t_ns > GST_WAIT_S * 1e9:
            self._emit(self._pending, None, out)
        if now - self._last_line_ns > self.config.silence_timeout_s * 1e9:
            self.counts["silences"] += 1
            self._drop(f"no NMEA sentence for {self.config.silence_timeout_s} s")
        return out

    def _on_line(self, raw: bytes, t_ns: int, out: list[GpsReading]) -> None:
        text = raw.strip(b"\r \x00")
        if not text:
            return
        self._last_line_ns = self._clock()
        self.counts["lines"] += 1
        start = text.rfind(b"$")
        if start < 0:
            self.counts["garbled"] += 1
            return
        if start > 0:  # sentences cut off by the next one's '$', or noise (any bytes) before it
            cut = text.count(b"$", 0, start)
            self.counts["truncated" if cut else "garbled"] += max(cut, 1)
        try:
            line = text[start:].decode("ascii")
        except UnicodeDecodeError:
            self.counts["garbled"] += 1
            return
        star = line.rfind("*")
        if star < 0 or len(line) - star != 3:
            self.counts["truncated"] += 1
            return
        try:
            msg = pynmea2.parse(line, check=True)
        except pynmea2.ChecksumError:
            self.counts["checksum"] += 1
            return
        except pynmea2.SentenceTypeError:
            self.sentence_types[line[1:6]] += 1
            return
        except (pynmea2.ParseError, ValueError):
            self.counts["malformed"] += 1
            return
        kind = getattr(msg, "sentence_type", "")
        self.sentence_types[f"{getattr(msg, 'talker', '')}{kind}"] += 1
        handler = {"GGA": self._on_gga, "GST": self._on_gst, "GSA": self._on_gsa, "RMC": self._on_rmc}.get(kind)
        if handler is not None:
            try:
                handler(msg, t_ns, out)
            except (ValueError, TypeError, AttributeError):
                self.counts["malformed"] += 1

    def _on_rmc(self, msg: Any, t_ns: int, out: list[GpsReading]) -> None:
        self._rmc_void_utc = msg.timestamp if msg.status == "V" else None

    def _on_gsa(self, msg: Any, t_ns: int, out: list[GpsReading]) -> None:
        self._vdop = _dop(msg.vdop)

    def _on_gga(self, msg: Any, t_ns: int, out: list[GpsReading]) -> None:
        if self._pending is not None:
            self._emit(self._pending, None, out)
        alt = _number(msg.altitude)
        if not msg.gps_qual or not msg.lat or not msg.lon or alt is None or self._rmc_void_utc == msg.timestamp:
            self.counts["no_fix"] += 1
            return
        lat = _degrees(msg.lat, msg.lat_dir, ("N", "S"), 90.0)
        lon = _degrees(msg.lon, msg.lon_dir, ("E", "W"), 180.0)
        # An empty geoid separation is 0 (receivers that give heights above the ellipsoid leave it out); one
        # that is there but not a number (a NUL slipped in passes the XOR checksum) makes the line malformed.
        geo_sep = 0.0 if msg.geo_sep in (None, "") else _number(msg.geo_sep)
        if geo_sep is None:
            self.counts["malformed"] += 1
            return
        height = alt + geo_sep
        if not isinstance(msg.gps_qual, int) or lat is None or lon is None or not abs(height) <= MAX_HEIGHT_M:
            self.counts["implausible"] += 1
            return
        sats = _number(msg.num_sats)
        epoch = _Epoch(t_ns, msg.timestamp, lat, lon, height, None if sats is None or not 0 <= sats < 256 else int(sats),
                       _dop(msg.horizontal_dil))
        if self._gst is not None and self._gst[0] == epoch.utc:
            self._emit(epoch, self._gst, out)
        elif self._expect_gst:
            self._pending = epoch
        else:
            self._emit(epoch, None, out)

    def _on_gst(self, msg: Any, t_ns: int, out: list[GpsReading]) -> None:
        sigmas = [_number(x) for x in (msg.std_dev_latitude, msg.std_dev_longitude, msg.std_dev_altitude)]
        if any(s is None or s <= 0.0 for s in sigmas):
            self.counts["gst_empty"] += 1
            return
        if any(s > MAX_SIGMA_M for s in sigmas):
            self.counts["gst_implausible"] += 1
            return
        self._expect_gst = self._gst_seen = True
        self._gst = (msg.timestamp, *sigmas)
        if self._pending is not None and self._pending.utc == msg.timestamp:
            self._emit(self._pending, self._gst, out)

    def _emit(self, epoch: _Epoch, gst: tuple | None, out: list[GpsReading]) -> None:
        if epoch is self._pending:
            self._pending = None
            if gst is None and not self._gst_seen:
                self._expect_gst = False  # this receiver sends no GST: stop waiting for it
        if gst is not None:
            sigma_h, sigma_v, source = horizontal_per_axis(math.hypot(gst[1], gst[2])), gst[3], "GST"
        elif epoch.hdop is not None and epoch.hdop > 0.0:
            (sigma_h, sigma_v), source = dop_sigmas(epoch.hdop, self._vdop, self.config.uere_m), "DOP"
        else:
            self.counts["no_accuracy"] += 1
            return
        p = self.local(epoch.lat, epoch.lon, epoch.alt)
        self.counts["fixes"] += 1
        out.append(GpsReading(GpsFix(epoch.t_ns, p, sigma_h, sigma_v), epoch.lat, epoch.lon, epoch.alt, source,
                              epoch.satellites, epoch.hdop))
