"""Crossbow IMU400CC serial driver: handshake, continuous streaming, reconnection.

``read()`` never raises: a lost port, a silent device or garbage on the line become counters,
a status line and reconnection attempts with back-off, so the estimator keeps running on
whatever arrives. Samples are dated on the host clock when their last byte arrived, rotated
into body FRD with the mounting ``R_BI``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from vtolpose.config.sections import SensorsSection
from vtolpose.drivers.imu.crossbow import CrossbowScale, Frame, PacketFramer, TimeCounter, checksum
from vtolpose.drivers.links.serial_link import LINK_ERRORS, Backoff, DeviceError, SerialLink
from vtolpose.estimator.core.measurements import ImuSample
from vtolpose.estimator.core.rotation import is_proper_rotation

__all__ = ["CrossbowConfig", "CrossbowImu", "DeviceIdentity", "ImuReading", "parse_serial_reply", "parse_version_reply"]

log = logging.getLogger(__name__)

PING, PONG = b"R", b"H"
SCALED_MODE, SCALED_ACK = b"c", b"C"
CONTINUOUS, POLLED = b"C", b"P"
VERSION, SERIAL_NUMBER = b"v", b"S"
_QUIET_S = 0.05  # line silence that ends a variable-length reply (several packet periods at 125 Hz)


@dataclass(slots=True)
class CrossbowConfig:
    """Port and model settings; the unconfirmed counter facts are configurable (INTERFACES.md)."""

    port: str
    baud: int = 38400
    scale: CrossbowScale = field(default_factory=CrossbowScale)
    counter: TimeCounter = field(default_factory=lambda: TimeCounter(7.9e-7, counts_down=True))
    R_BI: np.ndarray = field(default_factory=lambda: np.eye(3))
    reply_timeout_s: float = 0.5
    silence_timeout_s: float = 0.5
    reconnect_min_s: float = 0.5
    reconnect_max_s: float = 10.0

    def __post_init__(self) -> None:
        self.R_BI = np.asarray(self.R_BI, dtype=float).reshape(3, 3)
        if not is_proper_rotation(self.R_BI):
            raise ValueError(f"sensors.imu.R_BI: must be a proper rotation (orthonormal, det +1), got {self.R_BI.tolist()}")

    @classmethod
    def from_section(cls, sensors: SensorsSection, port: str | None = None, baud: int | None = None) -> "CrossbowConfig":
        """From ``sensors.imu`` and the drivers' shared back-off (``sensors.reconnect_*``), with optional
        command-line overrides."""
        imu = sensors.imu
        return cls(
            port=port or imu.port, baud=int(baud or imu.baud),
            scale=CrossbowScale(imu.rate_range_dps, imu.accel_range_g),
            counter=TimeCounter(imu.counter_tick_s, imu.counter_direction == "down"),
            R_BI=np.asarray(imu.R_BI, dtype=float), reply_timeout_s=imu.reply_timeout_s,
            silence_timeout_s=imu.silence_timeout_s,
            reconnect_min_s=sensors.reconnect_min_s, reconnect_max_s=sensors.reconnect_max_s,
        )


@dataclass(frozen=True, slots=True)
class DeviceIdentity:
    version: str | None
    serial_number: int | None
    notes: tuple[str, ...] = ()

    def describe(self) -> str:
        version = repr(self.version) if self.version is not None else "unknown"
        serial = f"{self.serial_number} (0x{self.serial_number:08X})" if self.serial_number is not None else "unknown"
        return f"version {version}, serial number {serial}" + "".join(f"; {n}" for n in self.notes)


@dataclass(frozen=True, slots=True)
class ImuReading:
    """One packet: sensor-axis values (what recordings store) and the body-frame sample."""

    t_ns: int
    gyro: np.ndarray       # sensor axes, rad/s
    accel: np.ndarray      # sensor axes, m/s²
    temperature_c: float
    counter: int
    device_ticks: int
    sample: ImuSample      # body FRD


def parse_version_reply(data: bytes) -> tuple[str | None, str | None]:
    """(version text, note) from ``0xFF, ASCII..., checksum``; the note says what was odd."""
    start = data.find(b"\xff")
    body = data[start + 1:] if start >= 0 else b""
    if len(body) < 2:
        return None, f"no version reply ({len(data)} bytes)"
    text = body[:-1].decode("ascii", errors="replace").strip("\x00 \r\n")
    if checksum(body[:-1]) != body[-1]:
        return text, "version reply checksum mismatch"
    return text, None


def parse_serial_reply(data: bytes) -> int | None:
    """The serial number from ``0xFF``, 4 big-endian bytes, checksum; None if malformed."""
    start = data.find(b"\xff")
    reply = data[start:start + 6] if start >= 0 else b""
    if len(reply) != 6 or checksum(reply[1:5]) != reply[5]:
        return None
    return int.from_bytes(reply[1:5], "big")


def _has_serial_reply(data: bytes) -> bool:
    start = data.find(b"\xff")
    return start >= 0 and len(data) - start >= 6


class CrossbowImu:
    """The IMU400CC on a serial port, streaming in continuous scaled mode."""

    def __init__(self, config: CrossbowConfig, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.config = config
        self._clock = clock
        self._link = SerialLink(config.port, config.baud, clock)
        self._framer = PacketFramer(config.counter, self._link.byte_time_ns)
        self._backoff = Backoff(config.reconnect_min_s, config.reconnect_max_s)
        self._R = config.R_BI
        self.identity: DeviceIdentity | None = None
        self.status = "closed"
        self.connects = 0
        self.silences = 0
        self.link_errors = 0
        self._last_packet_ns = 0
        self._closed = False

    # -- connection ---------------------------------------------------------------------------
    def open(self) -> DeviceIdentity:
        """Connect now; raises DeviceError/OSError with a message saying what to check."""
        self._closed = False
        try:
            return self._connect()
        except (DeviceError, *LINK_ERRORS):
            self._link.close()
            self._backoff.failed()
            raise

    def _connect(self) -> DeviceIdentity:
        cfg, link = self.config, self._link
        link.open()
        link.write(POLLED)  # stop a stream left running, so replies are not buried in packets
        link.discard_input(_QUIET_S, cfg.reply_timeout_s)
        self._command(PING, PONG, "ping")
        self._command(SCALED_MODE, SCALED_ACK, "scaled sensor mode")
        notes = []
        link.write(VERSION)
        version, note = parse_version_reply(link.read_for(cfg.reply_timeout_s, _QUIET_S))
        notes += [note] if note else []
        link.write(SERIAL_NUMBER)
        reply = link.read_for(cfg.reply_timeout_s, _QUIET_S, stop=_has_serial_reply)
        serial_number = parse_serial_reply(reply)
        if serial_number is None:
            notes.append(f"no valid serial number reply ({reply[:8].hex() or 'nothing'})")
        link.write(CONTINUOUS)
        self._framer.reset()
        self._last_packet_ns = self._clock()
        self._backoff.succeeded()
        self.connects += 1
        self.identity = DeviceIdentity(version, serial_number, tuple(notes))
        self.status = "streaming"
        log.info("IMU400CC on %s: %s", cfg.port, self.identity.describe())
        return self.identity

    def _command(self, command: bytes, answer: bytes, what: str) -> None:
        cfg = self.config
        self._link.write(command)
        reply = self._link.read_for(cfg.reply_timeout_s, cfg.reply_timeout_s, stop=lambda b: answer in b)
        if answer not in reply:
            got = f"got {reply[:16].hex()}" if reply else "got nothing"
            raise DeviceError(
                f"{cfg.port}: no {answer.decode()!r} answer to the {what} command {command.decode()!r} within "
                f"{cfg.reply_timeout_s} s ({got}); check power, cable and baud rate ({cfg.baud})")

    def _drop(self, reason: str) -> None:
        """Give up the current connection; ``read`` reconnects with back-off."""
        self._link.close()
        self._framer.reset()
        self.status = f"reconnecting: {reason}"
        log.warning("IMU on %s: %s; reconnecting", self.config.port, reason)

    def _try_connect(self, timeout_s: float) -> None:
        if not self._backoff.ready():
            time.sleep(min(timeout_s, self._backoff.wait_s()))
            return
        try:
            self._connect()
        except (DeviceError, *LINK_ERRORS) as exc:
            self._link.close()
            self._backoff.failed()
            status = f"reconnecting: {exc} (next try in {self._backoff.wait_s():.2f} s)"
            if not self.status.startswith(f"reconnecting: {exc}"):
                log.warning("IMU: %s", status)
            self.status = status

    def close(self) -> None:
        """Stop continuous mode (so the device is quiet for the next user) and release the port."""
        self._closed = True
        if self._link.is_open:
            try:
                self._link.write(POLLED)
            except LINK_ERRORS as exc:  # the device is gone: nothing to quieten, the port is released below
                log.debug("%s: could not stop continuous mode on close: %s", self._link, exc)
        self._link.close()
        self.status = "closed"

    def __enter__(self) -> "CrossbowImu":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- data ---------------------------------------------------------------------------------
    def read(self, timeout_s: float = 0.1) -> list[ImuReading]:
        """The packets that arrived within ``timeout_s`` (possibly none); never raises for I/O."""
        if self._closed:
            return []
        if not self._link.is_open:
            self._try_connect(timeout_s)
            return []
        try:
            data, t_ns = self._link.read(timeout_s)
        except Exception as exc:
            if self._closed:
                return []  # closed by another thread while this one was reading
            if not isinstance(exc, LINK_ERRORS):
                raise
            self.link_errors += 1
            self._drop(f"link error: {exc}")
            return []
        frames = self._framer.feed(data, t_ns) if data else []
        now = self._clock()
        if frames:
            self._last_packet_ns = now
        elif now - self._last_packet_ns > self.config.silence_timeout_s * 1e9:
            self.silences += 1
            self._drop(f"no packet for {self.config.silence_timeout_s} s")
        return [self._reading(f) for f in frames]

    def _reading(self, frame: Frame) -> ImuReading:
        gyro, accel, temperature = self.config.scale.decode(frame.words)
        sample = ImuSample(frame.t_ns, self._R @ gyro, self._R @ accel)
        return ImuReading(frame.t_ns, gyro, accel, temperature, frame.counter, frame.device_ticks, sample)

    def counts(self) -> dict[str, int]:
        """Packet and connection statistics (for status reports and the probe)."""
        return {**self._framer.stats.as_dict(), "connects": self.connects, "silences": self.silences,
                "link_errors": self.link_errors}

    @property
    def counter_step(self) -> int | None:
        """Learned time-counter ticks per packet (None until the stream is steady)."""
        return self._framer.step
