"""An NMEA 0183 GPS receiver on a pseudo-terminal: RMC, GGA, GSA and GST per epoch.

Epochs come from a dataset's ``gps0`` (converted to geodetic around an origin) or are given
directly. Each epoch's sentences are sent at its time (divided by ``speed``), paced by the
baud rate. ``mangle(epoch, sentence_type, line) -> bytes`` lets tests break single sentences.
"""

from __future__ import annotations

import datetime as dt
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pymap3d
import pynmea2

from vtolpose.drivers.emulators.pty_device import PtyDevice

__all__ = ["NmeaEmulator", "NmeaEpoch", "nmea_sentence"]

SENTENCES = ("RMC", "GGA", "GSA", "GST")


@dataclass(frozen=True, slots=True)
class NmeaEpoch:
    t_ns: int
    lat: float             # deg
    lon: float             # deg
    h: float               # ellipsoidal height [m]
    sigma_h: float = 0.5   # 1-sigma per horizontal axis [m] (GST)
    sigma_v: float = 1.0   # [m]
    quality: int = 1       # GGA fix quality: 0 = no fix
    satellites: int = 9
    hdop: float = 0.9
    vdop: float = 1.4


@dataclass(frozen=True, slots=True)
class SentSentence:
    epoch: int
    kind: str
    line: bytes
    intact: bool


def nmea_sentence(talker_and_type: str, fields: list[str]) -> bytes:
    """``$<body>*<checksum>\\r\\n`` with the XOR checksum of the body."""
    body = ",".join([talker_and_type, *fields])
    return f"${body}*{pynmea2.NMEASentence.checksum(body):02X}\r\n".encode("ascii")


def _angle(value: float, degree_digits: int) -> tuple[str, bool]:
    """``ddmm.mmmmmmm`` (or ``dddmm...``) and whether the value is negative."""
    minutes_total = round(abs(value) * 60.0, 7)
    degrees, minutes = divmod(minutes_total, 60.0)
    return f"{int(degrees):0{degree_digits}d}{minutes:010.7f}", value < 0


class NmeaEmulator(PtyDevice):
    def __init__(
        self,
        epochs: list[NmeaEpoch],
        *,
        baud: int = 9600,
        speed: float = 1.0,
        geoid_separation_m: float = 25.0,
        sentences: tuple[str, ...] = SENTENCES,
        talker: str = "GP",
        start_utc: dt.datetime = dt.datetime(2024, 5, 1, 12, 0, 0),
        mangle: Callable[[int, str, bytes], bytes] | None = None,
    ) -> None:
        super().__init__(baud)
        self.epochs, self.speed, self.geoid_separation_m = list(epochs), float(speed), geoid_separation_m
        self.sentence_types, self.talker, self.start_utc, self.mangle = sentences, talker, start_utc, mangle
        self.sent: list[SentSentence] = []
        self.finished = threading.Event()
        self.index = 0
        self._next_due: float | None = None

    @classmethod
    def from_dataset(cls, root: str | Path, origin: tuple[float, float, float] | None = None, **kwargs) -> "NmeaEmulator":
        """Epochs from the dataset's GPS (NED around its origin, or ``origin`` if it has none)."""
        from vtolpose.drivers.files.dataset import Dataset

        gps = Dataset.open(root).gps()
        if gps is None:
            raise ValueError(f"{root}: has no gps0 stream to emulate")
        lla0 = gps.origin_lla or origin
        if lla0 is None:
            raise ValueError(f"{root}: local-NED GPS without an origin; pass origin=(lat, lon, alt)")
        lat, lon, h = pymap3d.ned2geodetic(*gps.p_ned.T, *lla0)
        return cls([NmeaEpoch(int(t), float(a), float(b), float(c), float(sh), float(sv))
                    for t, a, b, c, sh, sv in zip(gps.t_ns, lat, lon, h, gps.sigma_h, gps.sigma_v)], **kwargs)

    def sentences(self, i: int) -> list[tuple[str, bytes]]:
        """The lines of epoch ``i``, in the order a receiver sends them."""
        e = self.epochs[i]
        utc = self.start_utc + dt.timedelta(microseconds=(e.t_ns - self.epochs[0].t_ns) // 1000)
        hms, date = utc.strftime("%H%M%S.") + f"{utc.microsecond // 10000:02d}", utc.strftime("%d%m%y")
        fix = e.quality > 0
        lat, south = _angle(e.lat, 2)
        lon, west = _angle(e.lon, 3)
        position = [lat, "S" if south else "N", lon, "W" if west else "E"] if fix else ["", "", "", ""]
        msl = e.h - self.geoid_separation_m
        lines = {
            "RMC": [hms, "A" if fix else "V", *position, "0.00", "", date, "", "", "A" if fix else "N"],
            "GGA": [hms, *position, str(e.quality), f"{e.satellites:02d}", f"{e.hdop:.1f}",
                    f"{msl:.3f}" if fix else "", "M", f"{self.geoid_separation_m:.3f}", "M", "", ""],
            "GSA": ["A", "3" if fix else "1", *[f"{p:02d}" if k < e.satellites and fix else "" for k, p in
                                               enumerate(range(2, 26, 2))],
                    f"{np.hypot(e.hdop, e.vdop):.1f}", f"{e.hdop:.1f}", f"{e.vdop:.1f}"],
            "GST": [hms, f"{e.sigma_h:.3f}", f"{e.sigma_h:.3f}", f"{e.sigma_h:.3f}", "0.0",
                    f"{e.sigma_h:.3f}", f"{e.sigma_h:.3f}", f"{e.sigma_v:.3f}"],
        }
        return [(kind, nmea_sentence(self.talker + kind, lines[kind])) for kind in self.sentence_types
                if fix or kind != "GST"]

    def on_tick(self, now: float) -> float:
        if self._next_due is None:
            self._next_due = now
        if self.silent or self.index >= len(self.epochs):
            return now + self.MAX_SLEEP_S
        if now < self._next_due:
            return self._next_due
        i = self.index
        n_bytes = 0
        for kind, line in self.sentences(i):
            data = self.mangle(i, kind, line) if self.mangle is not None else line
            self.send(data)
            n_bytes += len(data)
            self.sent.append(SentSentence(i, kind, line, data == line))
        self.index += 1
        if self.index >= len(self.epochs):
            self.finished.set()
            return now + self.MAX_SLEEP_S
        step = (self.epochs[self.index].t_ns - self.epochs[i].t_ns) * 1e-9 / self.speed
        self._next_due = max(self._next_due + step, now + self.tx_time_s(n_bytes))
        return self._next_due
