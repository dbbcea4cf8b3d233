"""Crossbow IMU400CC: the 18-byte scaled-mode packet, its scaling, and framing a noisy byte stream.

Pure code (no I/O): the serial driver is :mod:`vtolpose.drivers.imu.crossbow_serial`, the emulator
:mod:`vtolpose.drivers.emulators.imu400`. Packet (``../shared/spec/INTERFACES.md``): ``0xFF``, eight
big-endian 16-bit words (roll, pitch, yaw rate; accel x, y, z; temperature; time counter), then
the sum of the 16 data bytes mod 256.

Framing has to cope with ``0xFF`` inside data (every small negative word starts with one), so a
checksum alone would lock onto a false header about once in 256 tries. A candidate packet is
therefore also checked for being *in sequence* with the previous one: once the counter's step
per packet has been learned, its counter must be 1..``MAX_MISSING + 1`` steps on and its
temperature word within ``MAX_TEMPERATURE_STEP`` counts (temperature cannot jump in a few
milliseconds). A candidate that is not in sequence is taken only when the packet after it checks
out too (one packet of delay, only while regaining sync, e.g. after a reconnect).
"""

from __future__ import annotations

import math
import statistics
import struct
from collections import deque
from dataclasses import dataclass

import numpy as np

from vtolpose.estimator.core.calibration import STANDARD_GRAVITY

__all__ = [
    "COUNTER_MODULUS", "HEADER", "PACKET_LEN", "CrossbowScale", "Frame", "FramerStats", "PacketFramer",
    "TimeCounter", "checksum", "decode_packet", "encode_packet",
]

HEADER = 0xFF
PACKET_LEN = 18
COUNTER_MODULUS = 1 << 16
_WORDS = struct.Struct(">7hH")  # 3 rates, 3 accels, temperature (signed); time counter (unsigned)
_FULL_SCALE = 1.5 / 2**15  # a word of 2^15 is 1.5 × the model's range


def checksum(data: bytes | bytearray) -> int:
    return sum(data) & 0xFF


def encode_packet(words: tuple[int, ...] | list[int]) -> bytes:
    """The 18 bytes of a scaled-mode packet for 7 signed words and the unsigned counter."""
    body = _WORDS.pack(*words)
    return bytes([HEADER]) + body + bytes([checksum(body)])


def decode_packet(packet: bytes | bytearray) -> tuple[int, ...] | None:
    """The 8 words of an 18-byte packet, or None if its header or checksum is wrong."""
    if len(packet) != PACKET_LEN or packet[0] != HEADER or checksum(packet[1:17]) != packet[17]:
        return None
    return _WORDS.unpack_from(packet, 1)


@dataclass(frozen=True, slots=True)
class CrossbowScale:
    """Word ↔ SI conversion for a model with gyro range RR [°/s] and accel range GR [g]."""

    rate_range_dps: float = 100.0
    accel_range_g: float = 2.0
    gravity: float = STANDARD_GRAVITY

    @property
    def gyro_lsb(self) -> float:
        """rad/s per count."""
        return math.radians(self.rate_range_dps * _FULL_SCALE)

    @property
    def accel_lsb(self) -> float:
        """m/s² per count."""
        return self.accel_range_g * _FULL_SCALE * self.gravity

    def decode(self, words: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, float]:
        """(gyro [rad/s], accel [m/s²], temperature [°C]) in the sensor's axes."""
        gyro = np.array(words[0:3], dtype=float) * self.gyro_lsb
        accel = np.array(words[3:6], dtype=float) * self.accel_lsb
        return gyro, accel, 44.44 * (words[6] * 5.0 / 4096.0 - 1.375)

    def encode(self, gyro: np.ndarray, accel: np.ndarray, temperature_c: float) -> tuple[int, ...]:
        """The 7 signed words for these values, rounded and saturated as the device would."""
        counts = np.concatenate([np.asarray(gyro, float) / self.gyro_lsb, np.asarray(accel, float) / self.accel_lsb,
                                 [(temperature_c / 44.44 + 1.375) * 4096.0 / 5.0]])
        return tuple(int(c) for c in np.clip(np.rint(counts), -32768, 32767))


@dataclass(frozen=True, slots=True)
class TimeCounter:
    """The free-running 16-bit time word: tick length and count direction (both unconfirmed)."""

    tick_s: float
    counts_down: bool

    def delta(self, previous: int, current: int) -> int:
        """Ticks from ``previous`` to ``current`` modulo the wrap (0 .. 65535)."""
        d = previous - current if self.counts_down else current - previous
        return d % COUNTER_MODULUS

    def value(self, ticks: int) -> int:
        """The counter word after ``ticks`` ticks from zero (for emulators)."""
        return (-ticks if self.counts_down else ticks) % COUNTER_MODULUS


@dataclass(frozen=True, slots=True)
class Frame:
    """A packet found in the stream: its words, the host time its last byte arrived, and the
    unwrapped device time in ticks since the first packet of the session."""

    words: tuple[int, ...]
    t_ns: int
    device_ticks: int

    @property
    def counter(self) -> int:
        return self.words[7]


@dataclass(slots=True)
class FramerStats:
    good: int = 0           # packets delivered
    bad: int = 0            # times sync was lost: the expected packet was missing or corrupt
    rejected: int = 0       # checksum-valid candidates refused (counter implausible, not confirmed)
    resyncs: int = 0        # times sync was regained inside a session
    skipped_bytes: int = 0  # bytes discarded while hunting for a header
    lost: int = 0           # packets missing between two delivered ones, by the time counter

    def as_dict(self) -> dict[str, int]:
        return {k: getattr(self, k) for k in self.__slots__}


class PacketFramer:
    """Turns chunks of bytes (each with its host arrival time) into packets; never stalls.

    Decisions depend only on the bytes, not on how they were chunked, so a recorded byte stream
    always frames the same way.
    """

    MAX_MISSING = 5       # a counter jump of up to this many packets still counts as in sequence
    MAX_TEMPERATURE_STEP = 64  # temperature word counts (about 3.5 °C) allowed between packets
    WRAPS_FROM_HOST = 2   # host gaps longer than this many counter wraps add whole wraps
    STEP_HISTORY = 16     # counter steps remembered to learn the packet period in ticks
    MIN_STEPS = 8
    MAX_STEP_SPREAD = 0.1  # the step is trusted only if recent steps agree within 10 %

    def __init__(self, counter: TimeCounter, byte_time_ns: int) -> None:
        self.counter = counter
        self.byte_time_ns = int(byte_time_ns)
        self.stats = FramerStats()
        self._steps: deque[int] = deque(maxlen=self.STEP_HISTORY)
        self.step: int | None = None
        self._tolerance = 0
        self._buf = bytearray()
        self._last_t = 0  # host time of the last packet delivered (kept across sessions)
        self.reset()

    def reset(self) -> None:
        """Start a new session (after a reconnect): drop partial bytes and the counter anchor."""
        self.stats.skipped_bytes += len(self._buf)
        self._buf = bytearray()
        self._start = 0                           # stream offset of _buf[0]
        self._chunks: deque[tuple[int, int]] = deque()  # (end offset, host time) per chunk
        self._last_end: int | None = None             # stream offset after the last packet taken
        self._last_words: tuple[int, ...] | None = None
        self._ticks = 0
        self._synced = False
        self._damaged: tuple[int, bytes] | None = None  # (stream offset, bytes) of the last damaged packet

    def feed(self, data: bytes, t_ns: int) -> list[Frame]:
        if data:
            self._buf += data
            self._chunks.append((self._start + len(self._buf), int(t_ns)))
        return self._parse()

    def _parse(self) -> list[Frame]:
        out: list[Frame] = []
        buf, pos = self._buf, 0
        while True:
            i = buf.find(HEADER, pos)
            i = len(buf) if i < 0 else i
            if i > pos:
                self._lose_sync()
                self.stats.skipped_bytes += i - pos
                pos = i
            if len(buf) - pos < PACKET_LEN:
                break
            words = decode_packet(buf[pos:pos + PACKET_LEN])
            if words is not None:
                verdict = self._acceptable(pos, words)
                if verdict is None:
                    break  # wait for the next packet to confirm this one
                if verdict:
                    out.append(self._take(pos, words))
                    pos += PACKET_LEN
                    continue
                self.stats.rejected += 1
            if buf[pos] == HEADER:  # a damaged packet or a false header: see _shuffled_copy
                self._damaged = (self._start + pos, bytes(buf[pos:pos + PACKET_LEN]))
            self._lose_sync()
            self.stats.skipped_bytes += 1
            pos += 1
        del buf[:pos]
        self._start += pos
        while len(self._chunks) > 1 and self._chunks[1][0] <= self._start:
            self._chunks.popleft()  # the chunk before the buffer stays: its time bounds the next one
        return out

    def _lose_sync(self) -> None:
        if self._synced:
            self.stats.bad += 1
            self._synced = False

    def _acceptable(self, pos: int, words: tuple[int, ...]) -> bool | None:
        """True: take it; False: a false header; None: undecided until more bytes arrive."""
        if self._shuffled_copy(pos, words):
            return False
        if self._in_sequence(words):
            return True
        if self.step is None and self._last_end == self._start + pos and self._could_follow(self._last_words, words):
            return True  # contiguous with the previous packet, and no counter model yet
        after = pos + PACKET_LEN
        if len(self._buf) < after + PACKET_LEN:
            return None
        following = decode_packet(self._buf[after:after + PACKET_LEN])
        return following is not None and self._could_follow(words, following)

    def _shuffled_copy(self, pos: int, words: tuple[int, ...]) -> bool:
        """Whether the candidate at ``pos`` is more likely a damaged packet's bytes in the wrong order.

        A sum checksum cannot see bytes move. If a 0xFF is inserted inside a packet whose first
        data byte is 0xFF, the 18 bytes after its header are the packet with one 0xFF moved: a
        valid checksum, the right counter and temperature, garbled rates. The same 19 bytes
        also arise from a 0xFF inserted *before* a good packet that holds a 0xFF. Both readings
        (drop the first header, or drop an inner 0xFF) are valid; the one whose rates and
        accelerations continue the previous packet's is taken as the truth. When it is the
        other reading, the candidate is refused and the damaged packet is lost.
        """
        damaged, last = self._damaged, self._last_words
        if damaged is None or last is None or damaged[0] + 1 != self._start + pos or len(damaged[1]) < PACKET_LEN:
            return False
        bytes19 = damaged[1] + bytes(self._buf[pos + PACKET_LEN - 1:pos + PACKET_LEN])
        jump = sum(abs(a - b) for a, b in zip(words[:6], last[:6]))
        for k in range(2, PACKET_LEN + 1):
            other = decode_packet(bytes19[:k] + bytes19[k + 1:])
            if other is not None and self._could_follow(last, other):
                if sum(abs(a - b) for a, b in zip(other[:6], last[:6])) < jump:
                    return True
        return False

    def _in_sequence(self, words: tuple[int, ...]) -> bool:
        """Whether ``words`` can follow the last packet taken (needs a learned counter step)."""
        return self._last_words is not None and self._follows(self._last_words, words)

    def _could_follow(self, before: tuple[int, ...], words: tuple[int, ...]) -> bool:
        """``_follows`` once the counter step is known; before that only the temperature can be checked
        (without it a damaged packet whose checksum matches by chance, 1 in 256, would be taken)."""
        if self.step is None:
            return abs(words[6] - before[6]) <= self.MAX_TEMPERATURE_STEP
        return self._follows(before, words)

    def _follows(self, before: tuple[int, ...], words: tuple[int, ...]) -> bool:
        """Counter 1..MAX_MISSING + 1 steps after ``before``'s, temperature within reach of it."""
        if self.step is None or abs(words[6] - before[6]) > self.MAX_TEMPERATURE_STEP:
            return False
        d = self.counter.delta(before[7], words[7])
        for k in range(1, self.MAX_MISSING + 2):
            e = (d - k * self.step) % COUNTER_MODULUS
            if min(e, COUNTER_MODULUS - e) <= self._tolerance:
                return True
        return False

    def _time_of(self, offset: int) -> int:
        """Host time of the byte at stream ``offset``: its chunk's time, less the bytes after it."""
        floor = None
        for end, t in self._chunks:
            if offset < end:
                t_byte = t - (end - 1 - offset) * self.byte_time_ns
                return t_byte if floor is None else max(t_byte, floor)
            floor = t
        return self._chunks[-1][1]

    def _take(self, pos: int, words: tuple[int, ...]) -> Frame:
        start = self._start + pos
        t_ns = max(self._time_of(start + PACKET_LEN - 1), self._last_t + 1)  # strictly increasing
        if self._last_words is not None:
            ticks = self._unwrapped_ticks(words[7], t_ns)
            if self._last_end == start:
                self._learn_step(ticks)
            else:
                self.stats.resyncs += 1
            if self.step:
                self.stats.lost += max(0, round(ticks / self.step) - 1)
            self._ticks += ticks
        self.stats.good += 1
        self._last_end, self._last_words, self._last_t, self._synced = start + PACKET_LEN, words, t_ns, True
        return Frame(words, t_ns, self._ticks)

    def _unwrapped_ticks(self, counter: int, t_ns: int) -> int:
        """Counter ticks since the previous packet.

        The counter itself says how far it moved modulo one wrap; whole wraps are added only
        when the host clock says more than ``WRAPS_FROM_HOST`` wraps passed, because host
        arrival times jitter by tens of milliseconds (USB latency timers, scheduling).
        """
        d = self.counter.delta(self._last_words[7], counter)
        host_ticks = (t_ns - self._last_t) * 1e-9 / self.counter.tick_s
        if host_ticks <= self.WRAPS_FROM_HOST * COUNTER_MODULUS:
            return d
        return d + max(0, round((host_ticks - d) / COUNTER_MODULUS)) * COUNTER_MODULUS

    def _learn_step(self, ticks: int) -> None:
        self._steps.append(ticks)
        self.step, self._tolerance = None, 0
        if len(self._steps) < self.MIN_STEPS:
            return
        m = statistics.median(self._steps)
        near = [s for s in self._steps if abs(s - m) <= m / 2]
        spread = max(near) - min(near) if near else 0
        if m <= 0 or len(near) < self.MIN_STEPS or spread > self.MAX_STEP_SPREAD * m:
            return
        self.step = round(statistics.median(near))
        self._tolerance = max(3, 2 * spread)
