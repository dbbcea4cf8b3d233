"""The byte transports under a MAVLink endpoint: UDP (listening or sending), a TCP client, a serial port.

Every transport is non-blocking both ways and returns whole frames (:mod:`.mavlink_frames`) with
the peer they came from, so reading can be done in slices of bounded work and a slow link can
never block the caller: a stream transport keeps at most ``MAX_PENDING`` unsent bytes and drops
whole frames beyond that (counted). A listening UDP transport sends to the peers that have sent
valid MAVLink (the caller says which, :meth:`UdpTransport.confirm_peer`), at most ``max_peers`` of
them; a peer silent for ``peer_timeout_s`` gives its place to a newcomer. A sending UDP transport only
takes datagrams from the address it sends to. Datagrams the kernel had to drop because the socket's
buffer was full (a flood) are counted where the system says (Linux: ``kernel_dropped_datagrams``).
Stream transports open (and reopen a lost device or connection) in the background with back-off.
"""

from __future__ import annotations

import errno
import logging
import os
import select
import socket
import sys
import time
from collections import Counter
from typing import Any, Callable

from vtolpose.config.mavlink_settings import parse_mavlink_url
from vtolpose.drivers.links.mavlink_frames import StreamFramer, split_datagram
from vtolpose.drivers.links.serial_link import Backoff

__all__ = ["MAX_PENDING", "SerialTransport", "TcpTransport", "UdpTransport", "open_transport"]

log = logging.getLogger(__name__)

MAX_PENDING = 8192  # unsent bytes a stream transport holds before it drops whole frames
READ_CHUNK = 4096
UDP_MAX = 65535
_AGAIN = (errno.EAGAIN, errno.EWOULDBLOCK)
SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)  # Linux: each datagram carries the socket's drop count

Frames = list[tuple[bytes, Any]]  # (frame, peer)


class UdpTransport:
    """``udpin``/``udp`` (listen at HOST:PORT, answer the peers) or ``udpout`` (send to HOST:PORT)."""

    stream = False

    def __init__(self, url: str, max_peers: int = 4, peer_timeout_s: float = 10.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        scheme, _, rest = url.partition(":")
        host, _, port = rest.rpartition(":")
        self.listening = scheme in ("udpin", "udp")
        self.max_peers, self.peer_timeout_s, self._clock = max_peers, peer_timeout_s, clock
        self.counts: Counter[str] = Counter()
        self._peers: dict[tuple, float] = {}  # address -> last time it sent valid MAVLink
        self.sock = socket.socket(socket.AF_INET6 if ":" in host.strip("[]") else socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.setblocking(False)
            address = socket.getaddrinfo(host.strip("[]"), int(port), self.sock.family, socket.SOCK_DGRAM)[0][4]
            if self.listening:
                self.sock.bind(address)
                self.destination = None
            else:
                self.destination = address
        except OSError:
            self.sock.close()
            raise
        self._ancillary = self._ask_for_drop_counts()
        self._kernel_drops = 0  # the socket's drop count as last reported

    def _ask_for_drop_counts(self) -> int:
        """Room for the drop count the kernel attaches to each datagram, or 0 where it cannot."""
        if not sys.platform.startswith("linux"):
            return 0
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
        except OSError:
            return 0
        return socket.CMSG_SPACE(4)

    def _recv(self) -> tuple[bytes, Any]:
        if not self._ancillary:
            return self.sock.recvfrom(UDP_MAX)
        data, ancillary, _, address = self.sock.recvmsg(UDP_MAX, self._ancillary)
        for level, kind, value in ancillary:
            if level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL and len(value) >= 4:
                total = int.from_bytes(value[:4], sys.byteorder)  # dropped since the socket opened
                if total > self._kernel_drops:
                    self.counts["kernel_dropped_datagrams"] += total - self._kernel_drops
                    self._kernel_drops = total
        return data, address

    def fileno(self) -> int:
        return self.sock.fileno()

    def receive(self, max_datagrams: int) -> tuple[Frames, bool]:
        """Frames of up to ``max_datagrams`` waiting datagrams; True when more may be waiting."""
        frames: Frames = []
        for _ in range(max_datagrams):
            try:
                data, address = self._recv()
            except BlockingIOError:
                return frames, False
            except OSError as exc:  # ICMP port unreachable from an earlier send, and the like
                self.counts[f"receive_error_{errno.errorcode.get(exc.errno, exc.errno)}"] += 1
                continue
            if self.destination is not None and address[:2] != self.destination[:2]:
                self.counts["foreign_datagrams"] += 1
                continue
            found, left = split_datagram(data)
            if left:
                self.counts["bad_bytes"] += left
            frames.extend((frame, address) for frame in found)
        return frames, True

    def confirm_peer(self, address: Any) -> None:
        """``address`` sent valid MAVLink: (keep) sending to it, if a place is free."""
        if not self.listening:
            return
        now = self._clock()
        if address in self._peers:
            self._peers[address] = now
            return
        if len(self._peers) >= self.max_peers:
            self._expire(now)
        if len(self._peers) >= self.max_peers:
            self.counts["peers_refused_full"] += 1
            return
        self._peers[address] = now
        log.info("MAVLink peer %s joined", address)

    def _expire(self, now: float) -> None:
        """Make room: drop the peers silent for longer than ``peer_timeout_s``. Only a newcomer's need
        drops a peer, so a flood that hides a peer's messages for a while does not cut it off."""
        for address, seen in list(self._peers.items()):
            if now - seen > self.peer_timeout_s:
                del self._peers[address]
                self.counts["peers_expired"] += 1
                log.info("MAVLink peer %s dropped (silent %.0f s)", address, now - seen)

    @property
    def peers(self) -> list[Any]:
        return list(self._peers) if self.listening else [self.destination]

    def send(self, buf: bytes) -> int:
        """Send ``buf`` to every peer; the number it reached."""
        sent = 0
        for address in self.peers:
            try:
                self.sock.sendto(buf, address)
                sent += 1
            except OSError as exc:  # a full socket buffer or an unreachable peer: this message is lost
                self.counts[f"send_error_{errno.errorcode.get(exc.errno, exc.errno)}"] += 1
        return sent

    def service(self) -> None:
        """Nothing to keep up: peers are dropped only when a newcomer needs the place."""

    def close(self) -> None:
        self.sock.close()


class _StreamTransport:
    """Shared by serial and TCP: framing, a bounded send buffer, (re)opening with back-off.

    A subclass provides ``_start_open() -> bool`` (True: open now, False: still opening),
    ``_open_done() -> bool`` (raises OSError when opening failed), ``_read()``, ``_write()``, ``_close()``
    and ``fileno()``; none of them may block. ``before_close``, if set, is called while the open
    descriptor is still open, just before it is closed (a lost link, or :meth:`close`): whoever
    watches it for readability stops watching it before its number can be handed out again.
    """

    stream = True
    OPEN_TIMEOUT_S = 3.0

    def __init__(self, name: str, clock: Callable[[], float] = time.monotonic) -> None:
        self.name = name
        self.counts: Counter[str] = Counter()
        self.framer = StreamFramer()
        self.backoff = Backoff(0.5, 5.0, clock)
        self._clock = clock
        self._pending = bytearray()
        self.connected = False
        self._opening_since: float | None = None
        self.before_close: Callable[[], None] | None = None

    def receive(self, max_datagrams: int) -> tuple[Frames, bool]:
        """Frames from up to ``max_datagrams`` reads of at most READ_CHUNK bytes; True when more may wait."""
        if not self.connected:
            return [], False
        frames: Frames = []
        for _ in range(max_datagrams):
            try:
                data = self._read()
            except BlockingIOError:
                return frames, False
            except OSError as exc:
                self._lost(exc)
                return frames, False
            if not data:
                return frames, False
            junk = self.framer.junk_bytes
            frames.extend((frame, self.name) for frame in self.framer.feed(data))
            self.counts["bad_bytes"] += self.framer.junk_bytes - junk
        return frames, True

    def confirm_peer(self, address: Any) -> None:
        """A stream has one peer: the other end."""

    @property
    def peers(self) -> list[Any]:
        return [self.name] if self.connected else []

    def send(self, buf: bytes) -> int:
        if not self.connected:
            self.counts["dropped_not_connected"] += 1
            return 0
        if len(self._pending) + len(buf) > MAX_PENDING:
            self.counts["dropped_link_busy"] += 1
            return 0
        self._pending += buf
        self._flush()
        return 1

    def _flush(self) -> None:
        while self._pending and self.connected:
            try:
                n = self._write(bytes(self._pending))
            except BlockingIOError:
                return
            except OSError as exc:
                self._lost(exc)
                return
            if not n:
                return
            del self._pending[:n]

    def service(self) -> None:
        """Flush what waits; open (or reopen) the link when the back-off allows; never blocks."""
        if self.connected:
            self._flush()
            return
        try:
            if self._opening_since is None:
                if not self.backoff.ready():
                    return
                self._opening_since = self._clock()
                done = self._start_open()
            else:
                done = self._open_done()
                if not done and self._clock() - self._opening_since > self.OPEN_TIMEOUT_S:
                    raise TimeoutError("no answer")
        except OSError as exc:
            self._opening_since = None
            self.backoff.failed()
            self.counts["open_failures"] += 1
            self._quiet_close()
            (log.warning if self.counts["open_failures"] == 1 else log.debug)(
                "MAVLink %s: cannot open (%s); retrying with back-off", self.name, exc)
            return
        if done:
            self._opening_since = None
            self.connected = True
            self.backoff.succeeded()
            self.framer = StreamFramer()
            self._pending.clear()
            log.info("MAVLink %s: link open", self.name)

    def _lost(self, exc: BaseException) -> None:
        self.counts["link_lost"] += 1
        log.warning("MAVLink %s: link lost (%s); reopening with back-off", self.name, exc)
        self.connected = False
        self.backoff.failed()
        self._quiet_close()

    def _quiet_close(self) -> None:
        if self.before_close is not None:
            self.before_close()
        try:
            self._close()
        except OSError as exc:
            log.debug("MAVLink %s: close: %s", self.name, exc)

    def close(self) -> None:
        self._quiet_close()
        self.connected = False


class SerialTransport(_StreamTransport):
    """A serial port, 8N1, read and written without blocking."""

    def __init__(self, device: str, baud: int) -> None:
        super().__init__(device)
        self.device, self.baud = device, baud
        self._port: Any = None

    def _start_open(self) -> bool:
        import serial

        try:
            self._port = serial.Serial(self.device, self.baud, timeout=0, write_timeout=0, exclusive=True)
        except (serial.SerialException, ValueError) as exc:
            raise OSError(f"serial port {self.device}: {exc}") from None
        return True

    def _open_done(self) -> bool:
        return True

    def fileno(self) -> int | None:
        return self._port.fileno() if self.connected else None

    def _read(self) -> bytes:
        return self._port.read(READ_CHUNK)

    def _write(self, data: bytes) -> int:
        return os.write(self._port.fileno(), data)  # the port is non-blocking: writes what fits

    def _close(self) -> None:
        if self._port is not None:
            self._port.close()
            self._port = None


class TcpTransport(_StreamTransport):
    """A TCP client: connects without blocking, reconnects with back-off."""

    def __init__(self, host: str, port: int) -> None:
        super().__init__(f"tcp:{host}:{port}")
        self.address = (host, port)
        self._sock: socket.socket | None = None

    def _start_open(self) -> bool:
        family = socket.AF_INET6 if ":" in self.address[0] else socket.AF_INET
        self._sock = socket.socket(family, socket.SOCK_STREAM)
        self._sock.setblocking(False)
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        code = self._sock.connect_ex(self.address)
        if code == 0:
            return True
        if code in (errno.EINPROGRESS, errno.EALREADY, *_AGAIN):
            return False
        raise OSError(code, os.strerror(code))

    def _open_done(self) -> bool:
        if not select.select([], [self._sock], [], 0)[1]:
            return False
        code = self._sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        if code:
            raise OSError(code, os.strerror(code))
        return True

    def fileno(self) -> int | None:
        return self._sock.fileno() if self.connected and self._sock is not None else None

    def _read(self) -> bytes:
        data = self._sock.recv(READ_CHUNK)
        if not data:
            raise ConnectionResetError("closed by the peer")
        return data

    def _write(self, data: bytes) -> int:
        return self._sock.send(data)

    def _close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def open_transport(url: str, max_peers: int = 4, peer_timeout_s: float = 10.0) -> UdpTransport | _StreamTransport:
    """The transport for a MAVLink URL (``udpin``/``udp``/``udpout``/``tcp`` HOST:PORT, or a serial device[,BAUD])."""
    device, baud = parse_mavlink_url(url)
    scheme = url.partition(":")[0]
    if scheme in ("udpin", "udp", "udpout"):
        return UdpTransport(url, max_peers, peer_timeout_s)
    if scheme == "tcp":
        host, _, port = url.partition(":")[2].rpartition(":")
        return TcpTransport(host.strip("[]"), int(port))
    return SerialTransport(device, baud or 115200)
