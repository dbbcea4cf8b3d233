"""MAVLink 2 message signing: the shared key file, checking incoming signatures, stamping outgoing ones.

A signature is the first 6 bytes of SHA-256 over the key and the frame up to the signature, with
a 48-bit timestamp (10 µs units since 2015-01-01 UTC) that must rise per stream (link id, system,
component) so a recorded message cannot be played again. The checks here run in the order that
keeps a forger powerless: the signature first, and only an authentic message moves its stream's
timestamp. (pymavlink's own check records the timestamp before it compares the signature, so one
forged message with a far-future timestamp would lock the real sender out; and its table of streams
grows with every new triple a sender invents.) The table of authentic streams is bounded.
"""

from __future__ import annotations

import hashlib
import time
from collections import OrderedDict
from pathlib import Path

from vtolpose.config.mavlink_settings import key_file_problem

__all__ = ["SIGNATURE_LEN", "SignatureCheck", "SigningKeyError", "read_signing_key", "signing_timestamp"]

SIGNATURE_LEN = 13  # link id (1), timestamp (6), signature (6)
_EPOCH_2015 = 1420070400  # 2015-01-01T00:00:00Z, the signing timestamps' origin
_NEW_STREAM_SLACK = 60 * 100_000  # a new stream may start up to one minute behind the newest time seen
MAX_STREAMS = 64  # authentic (link, system, component) streams remembered; the oldest is forgotten first


class SigningKeyError(ValueError):
    """The signing key file is missing, not a 32-byte key, or readable by every user of the machine."""


def read_signing_key(path: str | Path) -> bytes:
    """32 raw bytes, or 64 hexadecimal characters (whitespace ignored), from a file only its owner
    (and group) may read: a key every local user can read is refused, not used."""
    path = Path(path)
    problem = key_file_problem(path)
    if problem is not None:
        raise SigningKeyError(f"signing key {problem}")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SigningKeyError(f"signing key file {path}: {exc.strerror or exc}") from None
    if len(data) == 32:
        return data
    text = data.decode("ascii", errors="replace").strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text)
        except ValueError:
            raise SigningKeyError(f"signing key file {path}: 64 characters, but not hexadecimal") from None
    raise SigningKeyError(f"signing key file {path}: expected 32 raw bytes or 64 hex characters, got {len(data)} bytes")


def signing_timestamp(now_s: float | None = None) -> int:
    """The signing clock now: 10 µs units since 2015-01-01 UTC."""
    return int(((time.time() if now_s is None else now_s) - _EPOCH_2015) * 100_000)


class SignatureCheck:
    """Verifies signed MAVLink 2 frames against one key; remembers at most ``max_streams`` streams."""

    def __init__(self, key: bytes, max_streams: int = MAX_STREAMS, now_s: float | None = None) -> None:
        if len(key) != 32:
            raise ValueError("a MAVLink signing key has 32 bytes")
        self._key = key
        self.max_streams = max_streams
        self.newest = signing_timestamp(now_s)  # newest authentic timestamp seen (or the clock at start)
        self._streams: OrderedDict[tuple[int, int, int], int] = OrderedDict()

    def problem(self, frame: bytes, system: int, component: int) -> str | None:
        """Why the signed ``frame`` must be refused, or None when it is authentic and new."""
        signature = frame[-6:]
        digest = hashlib.sha256(self._key + bytes(frame[:-6])).digest()[:6]
        if digest != signature:
            return "bad_signature"
        link_id = frame[-SIGNATURE_LEN]
        timestamp = int.from_bytes(frame[-12:-6], "little")
        stream = (link_id, system, component)
        last = self._streams.get(stream)
        if last is None:
            if timestamp + _NEW_STREAM_SLACK < self.newest:
                return "replayed"
        elif timestamp <= last:
            return "replayed"
        self._streams[stream] = timestamp
        self._streams.move_to_end(stream)
        while len(self._streams) > self.max_streams:
            self._streams.popitem(last=False)
        self.newest = max(self.newest, timestamp)
        return None

    @property
    def streams(self) -> int:
        return len(self._streams)
