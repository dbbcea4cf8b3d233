"""A device behind a pseudo-terminal: a background thread that answers bytes and sends its own.

The emulator keeps its own handle on the slave side open, so a driver closing and reopening the
port (as it does when reconnecting) does not hang the terminal up. Like a UART with nobody
listening, bytes that do not fit in the terminal's buffer are dropped (and counted), never
blocking the device.
"""

from __future__ import annotations

import logging
import os
import select
import threading
import time
import tty

__all__ = ["PtyDevice"]

log = logging.getLogger(__name__)


class PtyDevice:
    """Subclasses implement ``on_input(data, now)`` and ``on_tick(now) -> next wake-up time``."""

    MAX_SLEEP_S = 0.02

    def __init__(self, baud: int) -> None:
        self.baud = int(baud)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # a plain byte pipe: no echo, no line editing
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self.dropped_bytes = 0
        self.received = bytearray()  # every byte the driver wrote (commands), for tests
        self._silent_until = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.lock = threading.RLock()

    # -- lifecycle ------------------------------------------------------------------------------
    def start(self) -> "PtyDevice":
        self._thread = threading.Thread(target=self._run, name=f"{type(self).__name__}:{self.port}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError as exc:  # the peer's end may be gone first; close the other fd regardless
                log.debug("pty fd %d close: %s", fd, exc)

    def __enter__(self) -> "PtyDevice":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- behaviour shared by all devices ----------------------------------------------------------
    def tx_time_s(self, n_bytes: int) -> float:
        """How long ``n_bytes`` take on the wire (8N1) at this device's baud rate."""
        return n_bytes * 10.0 / self.baud

    def send(self, data: bytes) -> None:
        """Write to the line now; what the terminal buffer cannot take is lost, as on a real UART."""
        view = memoryview(data)
        while view:
            try:
                n = os.write(self._master, view)
            except BlockingIOError:
                self.dropped_bytes += len(view)
                return
            except OSError:
                return
            view = view[n:]

    def go_silent(self, duration_s: float) -> None:
        """Neither send nor hear anything for ``duration_s`` (a cable pulled, a brown-out)."""
        with self.lock:
            self._silent_until = time.monotonic() + duration_s

    @property
    def silent(self) -> bool:
        return time.monotonic() < self._silent_until

    def on_input(self, data: bytes, now: float) -> None:
        """Bytes the driver wrote."""

    def on_tick(self, now: float) -> float:
        """Do what is due at ``now``; return when to be called next."""
        return now + self.MAX_SLEEP_S

    def _run(self) -> None:
        wake = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            timeout = min(max(0.0, wake - now), self.MAX_SLEEP_S)
            try:
                readable, _, _ = select.select([self._master], [], [], timeout)
            except (OSError, ValueError):
                return
            now = time.monotonic()
            if readable:
                try:
                    data = os.read(self._master, 4096)
                except (BlockingIOError, OSError):
                    data = b""
                if data and not self.silent:
                    self.received += data
                    with self.lock:
                        self.on_input(data, now)
            with self.lock:
                wake = self.on_tick(time.monotonic())
