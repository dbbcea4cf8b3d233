"""An IMU400CC on a pseudo-terminal: answers the command set and streams a dataset's IMU samples.

Samples (sensor axes, SI) are quantised into real 18-byte scaled-mode packets and paced like the
device: at the dataset's sample times (divided by ``speed``), never faster than the baud rate
allows. The time counter runs on the device clock (dataset time plus any silence), with the
configured tick and direction. Tests can corrupt packets (``mangle``) and pull the cable
(``silences``) at chosen packet numbers, and read back exactly what was sent (``sent``).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from vtolpose.drivers.imu.crossbow import CrossbowScale, TimeCounter, checksum, encode_packet
from vtolpose.drivers.emulators.pty_device import PtyDevice

__all__ = ["Imu400Emulator", "SentPacket"]

DEFAULT_VERSION = "IMU400CC-100 emulated"
DEFAULT_SERIAL = 0x0A1B2C3D


@dataclass(frozen=True, slots=True)
class SentPacket:
    index: int            # sample number in the source series
    words: tuple[int, ...]
    intact: bool          # False if ``mangle`` changed its bytes
    sent_ns: int          # host monotonic time it was written to the line


class Imu400Emulator(PtyDevice):
    def __init__(
        self,
        t_ns: np.ndarray,
        gyro: np.ndarray,
        accel: np.ndarray,
        *,
        scale: CrossbowScale = CrossbowScale(),
        counter: TimeCounter = TimeCounter(7.9e-7, counts_down=True),
        baud: int = 38400,
        speed: float = 1.0,
        temperature_c: float = 25.0,
        version: str = DEFAULT_VERSION,
        serial_number: int = DEFAULT_SERIAL,
        counter_start: int = 0x1234,
        mangle: Callable[[int, bytes], bytes] | None = None,
        silences: dict[int, tuple[float, bool]] | None = None,
    ) -> None:
        """``silences[i] = (seconds, reboot)``: after packet ``i`` the line goes dead; with
        ``reboot`` the device comes back in polled mode and waits for commands."""
        super().__init__(baud)
        self.t_ns = np.asarray(t_ns, dtype=np.int64)
        self.words = [scale.encode(g, a, temperature_c) for g, a in zip(gyro, accel)]
        self.counter, self.speed = counter, float(speed)
        self.version, self.serial_number = version, int(serial_number)
        self.counter_start = int(counter_start)
        self.mangle = mangle
        self.silences = dict(silences or {})
        self.sent: list[SentPacket] = []
        self.finished = threading.Event()
        self.continuous = False
        self.index = 0
        self._next_due = 0.0
        self._paused_ns = 0  # device time spent silent: the counter keeps running
        self._reboot_when_back = False
        self._back_from_silence = False

    @classmethod
    def from_dataset(cls, root: str | Path, **kwargs) -> "Imu400Emulator":
        """Stream the dataset's ``imu0`` samples in sensor axes, as the device would give them."""
        from vtolpose.drivers.files.dataset import Dataset

        raw = Dataset.open(root).imu_raw()
        return cls(raw.t_ns, raw.gyro, raw.accel, **kwargs)

    def packet_words(self, i: int) -> tuple[int, ...]:
        """Sample ``i``'s words with the counter at its device time."""
        ticks = round((int(self.t_ns[i] - self.t_ns[0]) + self._paused_ns) * 1e-9 / self.counter.tick_s)
        return (*self.words[i], (self.counter_start + self.counter.value(ticks)) % 65536)

    def _send_packet(self, now: float) -> None:
        i = self.index
        words = self.packet_words(i)
        packet = encode_packet(words)
        data = self.mangle(i, packet) if self.mangle is not None else packet
        self.send(data)
        self.sent.append(SentPacket(i, words, data == packet, time.monotonic_ns()))
        self.index += 1
        if self.index >= len(self.t_ns):
            self.continuous = False
            self.finished.set()
        else:
            dt = int(self.t_ns[self.index] - self.t_ns[i]) * 1e-9 / self.speed
            self._next_due = max(self._next_due + dt, now + self.tx_time_s(len(data)))
        if i in self.silences:
            seconds, reboot = self.silences.pop(i)
            self.go_silent(seconds)
            self._paused_ns += int(seconds * self.speed * 1e9)
            self._reboot_when_back, self._back_from_silence = reboot, True

    def on_input(self, data: bytes, now: float) -> None:
        for byte in data:
            command = bytes([byte])
            if command == b"R":
                self.continuous = False
                self.send(b"H")
            elif command == b"c":
                self.send(b"C")
            elif command == b"r":
                self.send(b"R")
            elif command == b"P":
                self.continuous = False
            elif command == b"C" and self.index < len(self.t_ns):
                self.continuous, self._next_due = True, now
            elif command == b"G":
                if self.continuous:
                    self.continuous = False
                elif self.index < len(self.t_ns):
                    self._send_packet(now)
            elif command == b"v":
                text = self.version.encode("ascii")
                self.send(b"\xff" + text + bytes([checksum(text)]))
            elif command == b"S":
                number = self.serial_number.to_bytes(4, "big")
                self.send(b"\xff" + number + bytes([checksum(number)]))

    def on_tick(self, now: float) -> float:
        if self.silent:
            return now + self.MAX_SLEEP_S
        if self._back_from_silence:  # resume the schedule from now rather than burst
            self._back_from_silence, self._next_due = False, now
            if self._reboot_when_back:
                self._reboot_when_back, self.continuous = False, False
        while self.continuous and now >= self._next_due and not self.silent:
            self._send_packet(now)
        return self._next_due if self.continuous else now + self.MAX_SLEEP_S
