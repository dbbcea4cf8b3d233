"""MAVLink 2 frames built here, for the one message sent at the IMU rate, on pymavlink's own link state.

pymavlink frames a message through a message object, a generic header object and several small
steps; for ODOMETRY at every IMU sample that is a fair share of the estimator's loop. :func:`send_v2`
frames an already packed payload the way pymavlink's ``MAVLink.send`` does, and keeps the state in
the same ``MAVLink`` object, so messages that still go through pymavlink on that link (HEARTBEAT,
STATUSTEXT, TIMESYNC) carry on from it:

- header: magic 0xFD, payload length, incompatibility flags (1 when signing outgoing), compatibility
  flags 0, the link's sequence number, system and component ids, the 24-bit message id;
- payload: trailing zero bytes cut (MAVLink 2), but never below one byte;
- checksum: CRC-16/MCRF4XX over the header after the magic, the payload and the message's CRC extra;
- signature (when signing outgoing): link id, the 48-bit signing timestamp, then the first 6 bytes of
  SHA-256 over the key and the whole frame so far; the link's timestamp then moves on by one;
- after the frame is written: the sequence number moves on (mod 256), the sent totals count it
  (a pymavlink send callback is not called: there is no message object to give it; none is set here).

A test frames many messages both ways and holds the bytes identical.
"""

from __future__ import annotations

import hashlib
import struct
from typing import Any

from fastcrc.crc16 import mcrf4xx

__all__ = ["frame_v2", "send_v2"]

MAGIC_V2 = 0xFD
IFLAG_SIGNED = 0x01
_HEADER = struct.Struct("<BBBBBBBHB")
_LINK_AND_TIMESTAMP = struct.Struct("<BQ")  # the signature block's first 7 bytes are the first 7 of this


def frame_v2(tx: Any, msg_id: int, crc_extra: int, payload: bytes) -> bytes:
    """The whole frame of ``payload`` (packed, not yet cut) on link ``tx`` (a pymavlink ``MAVLink``);
    advances the link's signing timestamp when it signs, as pymavlink does while packing."""
    body = payload.rstrip(b"\0") or payload[:1]
    signing = tx.signing
    signed = signing.sign_outgoing
    header = _HEADER.pack(MAGIC_V2, len(body), IFLAG_SIGNED if signed else 0, 0, tx.seq, tx.srcSystem,
                          tx.srcComponent, msg_id & 0xFFFF, msg_id >> 16)
    crc = mcrf4xx(bytes((crc_extra,)), mcrf4xx(body, mcrf4xx(header[1:], 0xFFFF)))
    frame = header + body + crc.to_bytes(2, "little")
    if not signed:
        return frame
    frame += _LINK_AND_TIMESTAMP.pack(signing.link_id, signing.timestamp)[:7]
    signing.timestamp += 1
    return frame + hashlib.sha256(signing.secret_key + frame).digest()[:6]


def send_v2(tx: Any, msg_id: int, crc_extra: int, payload: bytes) -> None:
    """Frame ``payload`` and write it to ``tx.file``, with the bookkeeping of pymavlink's ``send``."""
    frame = frame_v2(tx, msg_id, crc_extra, payload)
    tx.file.write(frame)
    tx.seq = (tx.seq + 1) % 256
    tx.total_packets_sent += 1
    tx.total_bytes_sent += len(frame)
