"""STATUSTEXT for the operator: what changed in the status document, rate-limited, in 50-byte chunks.

Once a second the runtime hands the outputs its status document; :class:`StatusEvents` compares it
with the previous one and names what an operator must know: a filter reset (and why), a sensor going
stale or coming back, the heading placed (or lost), while the visual-inertial start waits, why
(once per change of the check that holds it, with what it measured), and a GPS whose claimed accuracy is not
believed ("GPS claims 0.005 m, behaves like 1.9 m"). :class:`TextLimiter` lets at most ``per_minute``
texts out (a short burst allowed), and says how many it held back once it lets one out again, so a
flapping sensor cannot flood a radio link. Long texts are split into chunks that share an ``id``
(the MAVLink 2 extension ground stations reassemble); at most four chunks, the rest cut.
"""

from __future__ import annotations

import time
from typing import Any, Callable, Iterator

from vtolpose.drivers.links.mavlink_wire import mavutil

__all__ = ["StatusEvents", "TextLimiter", "statustext_chunks"]

mav = mavutil.mavlink
PREFIX = "vtolpose: "
CHUNK = 50
MAX_CHUNKS = 4
BURST = 5


class StatusEvents:
    """The operator-level changes between successive status documents, as (severity, text)."""

    def __init__(self) -> None:
        self._aligned = False
        self._resets = 0
        self._stale: set[str] = set()
        self._waiting: str | None = None  # the check holding the visual-inertial start, last said
        self._gps_noise: str | None = None

    def changes(self, doc: dict[str, Any]) -> list[tuple[int, str]]:
        health = doc.get("health") or {}
        aligned = bool(doc.get("heading_aligned"))
        resets = int(doc.get("filter_resets") or 0)
        stale = {name for name, s in (health.get("sensors") or {}).items() if isinstance(s, dict) and s.get("stale")}
        out: list[tuple[int, str]] = []
        if resets > self._resets:
            last = health.get("last_reset") or {}
            count = "filter reset" if resets - self._resets == 1 else f"{resets - self._resets} filter resets, the last"
            out.append((mav.MAV_SEVERITY_WARNING, f"{count} ({last.get('kind', '?')}): {last.get('reason', '')}".rstrip(": ")))
        if aligned != self._aligned:
            out.append((mav.MAV_SEVERITY_INFO, "heading aligned, pose usable") if aligned
                       else (mav.MAV_SEVERITY_WARNING, "heading not aligned, pose not usable"))
        out += [(mav.MAV_SEVERITY_WARNING, f"{name} stale") for name in sorted(stale - self._stale)]
        out += [(mav.MAV_SEVERITY_INFO, f"{name} back") for name in sorted(self._stale - stale)]
        waiting = doc.get("visual_start") or {}
        if waiting.get("check") != self._waiting and waiting.get("text"):
            out.append((mav.MAV_SEVERITY_INFO, waiting["text"]))
        gps_noise = (doc.get("gps_noise") or {}).get("text")
        if gps_noise != self._gps_noise:
            out.append((mav.MAV_SEVERITY_WARNING, gps_noise) if gps_noise
                       else (mav.MAV_SEVERITY_INFO, "GPS accuracy claims believed again"))
        self._aligned, self._resets, self._stale, self._gps_noise = aligned, resets, stale, gps_noise
        self._waiting = waiting.get("check")
        return out


class TextLimiter:
    """A token bucket: ``per_minute`` texts a minute, bursts of up to five; counts what it holds back."""

    def __init__(self, per_minute: int, clock: Callable[[], float] = time.monotonic) -> None:
        self.rate_per_s = per_minute / 60.0
        self.capacity = float(min(BURST, per_minute))
        self._tokens = self.capacity
        self._clock = clock
        self._last = clock()
        self.suppressed = 0  # held back since the last text let out
        self.suppressed_total = 0

    def admit(self, texts: list[tuple[int, str]]) -> list[tuple[int, str]]:
        now = self._clock()
        self._tokens = min(self.capacity, self._tokens + (now - self._last) * self.rate_per_s)
        self._last = now
        out = []
        for severity, text in texts:
            if self._tokens < 1.0:
                self.suppressed += 1
                self.suppressed_total += 1
                continue
            self._tokens -= 1.0
            if self.suppressed:
                text = f"{text} ({self.suppressed} earlier held back)"
                self.suppressed = 0
            out.append((severity, text))
        return out


def statustext_chunks(text: str, chunk_id: int) -> Iterator[tuple[bytes, int, int]]:
    """(text bytes, id, chunk_seq) for ``text``: one message with id 0 when it fits, else chunks sharing
    ``chunk_id`` (1..65535), the last one shorter than 50 bytes so receivers see it end."""
    data = (PREFIX + text).encode("ascii", errors="replace")[: CHUNK * MAX_CHUNKS - 1]
    if len(data) <= CHUNK:
        yield data, 0, 0
        return
    starts = range(0, len(data), CHUNK)
    for seq, start in enumerate(starts):
        yield data[start:start + CHUNK], chunk_id, seq
    if len(data) % CHUNK == 0:
        yield b"", chunk_id, len(starts)  # an empty (all-NUL) chunk ends a text of whole chunks
