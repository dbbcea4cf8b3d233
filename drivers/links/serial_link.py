"""A serial port read in host-timestamped chunks, and the back-off used to reopen lost devices.

Field devices get unplugged, browned out and re-enumerated; drivers must never hammer a dead
port nor give up on it. :class:`Backoff` spaces reconnection attempts (doubling up to a cap);
:class:`SerialLink` wraps pyserial so each read says *when* its bytes arrived on the host clock.
"""

from __future__ import annotations

import logging
import time
from typing import Callable

import serial

__all__ = ["BITS_PER_BYTE", "Backoff", "DeviceError", "LINK_ERRORS", "SerialLink"]

log = logging.getLogger(__name__)

# What a lost or misbehaving port raises: callers catch these, count them and reconnect.
LINK_ERRORS = (OSError, serial.SerialException)
BITS_PER_BYTE = 10  # 8N1: start bit, 8 data bits, stop bit


class DeviceError(RuntimeError):
    """The port opened but the device did not answer as expected; the message says what to check."""


class Backoff:
    """Delays between reconnection attempts: ``min_s``, doubling after each failure up to ``max_s``."""

    def __init__(self, min_s: float, max_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        if not 0.0 < min_s <= max_s:
            raise ValueError(f"back-off needs 0 < min_s <= max_s, got {min_s}, {max_s}")
        self.min_s, self.max_s, self._clock = min_s, max_s, clock
        self.delay_s = min_s
        self._next_attempt = 0.0
        self.failures = 0

    def ready(self) -> bool:
        return self._clock() >= self._next_attempt

    def wait_s(self) -> float:
        """Seconds until the next attempt is allowed (0 if now)."""
        return max(0.0, self._next_attempt - self._clock())

    def failed(self) -> None:
        self.failures += 1
        self._next_attempt = self._clock() + self.delay_s
        self.delay_s = min(self.delay_s * 2.0, self.max_s)

    def succeeded(self) -> None:
        self.delay_s = self.min_s
        self._next_attempt = 0.0


class SerialLink:
    """One serial port (8N1, no flow control), opened exclusively, read in timestamped chunks."""

    def __init__(self, port: str, baud: int, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.port, self.baud, self._clock = port, int(baud), clock
        self._serial: serial.Serial | None = None
        self._timeout: float | None = None

    @property
    def is_open(self) -> bool:
        return self._serial is not None

    @property
    def byte_time_ns(self) -> int:
        """How long one byte takes on the wire at this baud rate."""
        return BITS_PER_BYTE * 1_000_000_000 // self.baud

    def open(self) -> None:
        """Open the port; raises OSError/SerialException with pyserial's reason (missing, busy, ...)."""
        self.close()
        s = serial.Serial()
        s.port, s.baudrate, s.timeout, s.write_timeout = self.port, self.baud, 0.0, 1.0
        s.exclusive = True  # a second process on the same IMU port would steal bytes
        s.open()
        self._serial, self._timeout = s, 0.0

    def close(self) -> None:
        s, self._serial = self._serial, None
        if s is not None:
            try:
                s.close()
            except LINK_ERRORS as exc:  # an unplugged adapter: the port is released either way
                log.debug("%s: close: %s", self.port, exc)

    def _port(self) -> serial.Serial:
        if self._serial is None:
            raise serial.SerialException(f"{self.port}: not open")
        return self._serial

    def read(self, timeout_s: float) -> tuple[bytes, int]:
        """Wait up to ``timeout_s`` for bytes; return all that arrived and the host time [ns] now.

        The time is when the last returned byte was already on the host, so callers can date
        earlier bytes of the chunk by subtracting whole byte times.
        """
        s = self._port()
        if self._timeout != timeout_s:
            s.timeout, self._timeout = timeout_s, timeout_s
        data = s.read(1)
        if data:
            waiting = s.in_waiting
            if waiting:
                data += s.read(waiting)
        return data, self._clock()

    def write(self, data: bytes) -> None:
        s = self._port()
        s.write(data)
        s.flush()

    def discard_input(self, quiet_s: float, max_s: float) -> int:
        """Read and drop bytes until the line has been quiet for ``quiet_s`` (at most ``max_s``).

        Used after stopping a streaming device, so a stale packet cannot be taken for a reply.
        Returns the number of bytes dropped.
        """
        dropped = 0
        deadline = time.monotonic() + max_s
        while time.monotonic() < deadline:
            data, _ = self.read(min(quiet_s, max(0.0, deadline - time.monotonic())))
            if not data:
                break
            dropped += len(data)
        self._port().reset_input_buffer()
        return dropped

    def read_for(self, duration_s: float, quiet_s: float, stop: Callable[[bytes], bool] | None = None) -> bytes:
        """Collect bytes for up to ``duration_s``; end early after ``quiet_s`` of silence once some
        arrived, or as soon as ``stop(collected)`` is true."""
        out = b""
        deadline = time.monotonic() + duration_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0.0:
                return out
            data, _ = self.read(min(left, quiet_s) if out else left)
            if not data and out:
                return out
            out += data
            if stop is not None and stop(out):
                return out
