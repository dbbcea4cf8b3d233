"""MAVLink frames off a link: cut from a datagram or a byte stream, then decoded and checked.

Nothing a link delivers is used before it passes :class:`Inbound`: a whole frame of a message id
this dialect knows, with a correct checksum, and, when a signing key is set, signed with that key
(unsigned frames only when signing is not required); a signature is checked before the frame is decoded. What fails is counted under its reason and
dropped; a message id the dialect does not know is never counted as received, and is refused when
signing is required (its checksum cannot be verified, and it cannot be let past the signature rule).
"""

from __future__ import annotations

from collections import Counter

from vtolpose.drivers.links.mavlink_signing import SIGNATURE_LEN, SignatureCheck
from vtolpose.drivers.links.mavlink_wire import mavutil

__all__ = ["Inbound", "StreamFramer", "frame_header", "frame_length", "split_datagram"]

mav = mavutil.mavlink
MAGIC_V1, MAGIC_V2 = 0xFE, 0xFD
IFLAG_SIGNED = 0x01
MAGICS = (MAGIC_V1, MAGIC_V2)


def frame_length(buf: bytes | bytearray, start: int) -> int | None:
    """Length of the frame whose magic byte is ``buf[start]``; None while its header is incomplete."""
    if buf[start] == MAGIC_V2:
        if len(buf) - start < 3:
            return None
        return 12 + buf[start + 1] + (SIGNATURE_LEN if buf[start + 2] & IFLAG_SIGNED else 0)
    if len(buf) - start < 2:
        return None
    return 8 + buf[start + 1]


def frame_header(frame: bytes | bytearray) -> tuple[int, int, int, bool]:
    """(message id, system, component, signed) of a whole frame."""
    if frame[0] == MAGIC_V2:
        return frame[7] | frame[8] << 8 | frame[9] << 16, frame[5], frame[6], bool(frame[2] & IFLAG_SIGNED)
    return frame[5], frame[3], frame[4], False


def split_datagram(data: bytes) -> tuple[list[bytes], int]:
    """The frames of one UDP datagram, back to back from its first byte, and the count of bytes left
    over that are no frame (a datagram that does not start with a frame is all left over)."""
    frames = []
    i = 0
    while i < len(data):
        n = frame_length(data, i) if data[i] in MAGICS else None
        if n is None or i + n > len(data):
            return frames, len(data) - i
        frames.append(data[i:i + n])
        i += n
    return frames, 0


def _checksum_ok(frame: bytes | bytearray) -> bool:
    msg_id = frame_header(frame)[0]
    cls = mav.mavlink_map.get(msg_id)
    if cls is None:
        return False
    end = len(frame) - (SIGNATURE_LEN if frame[0] == MAGIC_V2 and frame[2] & IFLAG_SIGNED else 0)
    crc = mav.x25crc(bytes(frame[1:end - 2]) + bytes([cls.crc_extra])).crc
    return crc == frame[end - 2] | frame[end - 1] << 8


class StreamFramer:
    """Frames from a byte stream (serial, TCP). Bytes before a magic byte are skipped; a candidate frame
    of an unknown message id or with a wrong checksum is taken for junk that held a magic byte, and the
    search resumes one byte after it. At most ``max_buffer`` bytes wait for the rest of a frame."""

    def __init__(self, max_buffer: int = 4096) -> None:
        self.max_buffer = max_buffer
        self._buf = bytearray()
        self.junk_bytes = 0

    def feed(self, data: bytes) -> list[bytes]:
        buf = self._buf
        buf += data
        frames = []
        i = 0
        while i < len(buf):
            if buf[i] not in MAGICS:
                j = min((k for k in (buf.find(MAGIC_V1, i), buf.find(MAGIC_V2, i)) if k >= 0), default=len(buf))
                self.junk_bytes += j - i
                i = j
                continue
            n = frame_length(buf, i)
            if n is None or i + n > len(buf):
                break  # wait for more bytes
            frame = bytes(buf[i:i + n])
            if _checksum_ok(frame):
                frames.append(frame)
                i += n
            else:
                self.junk_bytes += 1
                i += 1
        del buf[:i]
        if len(buf) > self.max_buffer:  # cannot happen with real frames (at most 280 bytes): junk
            self.junk_bytes += len(buf)
            buf.clear()
        return frames


class Inbound:
    """Decodes one link's frames and decides which may be used; ``counts`` says what became of the rest."""

    def __init__(self, key: bytes | None = None, require_signing: bool = False) -> None:
        if require_signing and key is None:
            raise ValueError("requiring signed messages needs the signing key")
        self._decoder = mav.MAVLink(None)  # no key here: signatures are checked by SignatureCheck
        self.check = SignatureCheck(key) if key is not None else None
        self.require_signing = require_signing
        self.counts: Counter[str] = Counter()

    def accept(self, frame: bytes) -> object | None:
        """The decoded message when ``frame`` may be used, else None (counted).

        With a key, a signed frame's signature is checked before anything in it is decoded: a forged
        frame costs a hash, never the decoder's work, and none of its fields is ever looked at."""
        msg_id, system, component, signed = frame_header(frame)
        if self.require_signing and not signed:
            self.counts["refused_unsigned"] += 1
            return None
        if msg_id not in mav.mavlink_map:
            self.counts["refused_unknown_id" if self.require_signing else "unknown_id"] += 1
            return None
        if self.check is not None and signed:
            problem = self.check.problem(frame, system, component)
            if problem is not None:
                self.counts[f"refused_{problem}"] += 1
                return None
        try:
            msg = self._decoder.decode(bytearray(frame))
        except mav.MAVError:
            self.counts["bad_data"] += 1
            return None
        if self.check is not None:
            self.counts["signed" if signed else "unsigned_accepted"] += 1
        self.counts["received"] += 1
        return msg
