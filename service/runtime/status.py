"""What ``<prefix>/status`` says once a second: sensor rates and ages, map size, rejections, resets, load.

Rates and ages are measured on the host's monotonic clock at arrival, so a stalled device shows
as a growing age even while the others keep the estimator running.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from vtolpose.estimator import Estimator, FusionCore, OutputPose


log = logging.getLogger(__name__)

# Quality: 100 at or below the "good" sigma, falling on a log scale to 1 at the "poor" one.
_POS_SIGMA_GOOD_M, _POS_SIGMA_POOR_M = 0.1, 10.0
_ATT_SIGMA_GOOD_RAD, _ATT_SIGMA_POOR_RAD = math.radians(0.5), math.radians(20.0)
_POS_DECADES = math.log10(_POS_SIGMA_POOR_M / _POS_SIGMA_GOOD_M)
_ATT_DECADES = math.log10(_ATT_SIGMA_POOR_RAD / _ATT_SIGMA_GOOD_RAD)


def pose_problem(pose: OutputPose, diagonal: list[float] | None = None) -> str | None:
    """Why ``pose`` must not be used for navigation, or None: no position yet, heading not aligned, a covariance
    that is not finite (or a negative variance), or the filter's health capping it to 0.

    A camera-only filter that never heard a GPS works in a frame of its own (``local_position``):
    its origin is where it started and its heading, unless one was known, the one it started with.
    Such a pose is usable relative to that frame, and its covariance says so (``published_cov9``).
    ``diagonal``: ``pose.cov9``'s diagonal as a list, when the caller already has it."""
    if not (pose.position_initialized or pose.local_position):
        return "no position"
    if not (pose.heading_aligned or pose.local_position):
        return "heading not aligned"
    d = pose.cov9.diagonal().tolist() if diagonal is None else diagonal
    for x in (d[0], d[1], d[2], d[6], d[7], d[8]):  # a loop, not a generator: this runs for every pose
        if not (math.isfinite(x) and x >= 0.0):
            return "covariance not finite"
    if pose.quality_cap <= 0:
        return "health"
    return None


# A placed heading is "weak" while its sigma exceeds this: 5° puts a point 20 m away 1.7 m off sideways.
HEADING_WEAK_SIGMA_RAD = math.radians(5.0)


def heading_weak(pose: OutputPose, diagonal: list[float] | None = None) -> bool:
    """Whether the heading, placed but still poorly known, deserves a word in the pose's status."""
    var = float(pose.cov9[8, 8]) if diagonal is None else diagonal[8]
    return pose.heading_aligned and not (math.isfinite(var) and var <= HEADING_WEAK_SIGMA_RAD**2)


def pose_quality(pose: OutputPose, diagonal: list[float] | None = None) -> int:
    """0 = invalid (:func:`pose_problem`); else 1–100 from the largest position and attitude sigmas, never
    above the filter's health cap (a stale sensor, a recent reset: ``estimator.health``)."""
    d = pose.cov9.diagonal().tolist() if diagonal is None else diagonal
    return 0 if pose_problem(pose, d) is not None else usable_pose_quality(pose, d)


def usable_pose_quality(pose: OutputPose, diagonal: list[float] | None = None) -> int:
    """:func:`pose_quality` of a pose already known to have no :func:`pose_problem` (it is not asked again)."""
    d = pose.cov9.diagonal().tolist() if diagonal is None else diagonal
    q = min(_score(math.sqrt(max(d[0:3])), _POS_SIGMA_GOOD_M, _POS_DECADES),
            _score(math.sqrt(max(d[6:9])), _ATT_SIGMA_GOOD_RAD, _ATT_DECADES))
    return min(max(1, int(round(100.0 * q))), pose.quality_cap)


def _score(sigma: float, good: float, decades: float) -> float:
    """1 at or below ``good``, 0 at ``decades`` decades above it, log-linear between."""
    return 1.0 - min(max(math.log10(max(sigma, 1e-12) / good) / decades, 0.0), 1.0)


def resident_memory_mb() -> float | None:
    """Current resident set size of this process [MB] (Linux /proc), None where unavailable."""
    try:
        with open("/proc/self/statm", encoding="ascii") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return pages * os.sysconf("SC_PAGE_SIZE") / 1e6


async def stopped_within(stop: asyncio.Event, seconds: float) -> bool:
    """Sleep up to ``seconds``, ending early when ``stop`` is set; True if it was (periodic tasks)."""
    try:
        await asyncio.wait_for(stop.wait(), timeout=seconds)
    except asyncio.TimeoutError:
        return False
    return True


@dataclass
class _Failures:
    count: int = 0
    last: str = ""
    first: BaseException | None = None
    logged_at: float | None = None
    since_logged: int = 0


class FailureBook:
    """Failures of the parts around the estimator (an output, a source, the trajectory file), isolated.

    A failing part must degrade the service, never stop it: each failure is counted under its
    part's name; the first is logged with its traceback, later ones as one summary line per
    ``period_s`` at most, so a link that fails 200 times a second cannot flood the log.
    """

    def __init__(self, period_s: float = 10.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.period_s = period_s
        self.clock = clock
        self.parts: dict[str, _Failures] = {}

    def record(self, part: str, exc: BaseException) -> None:
        f = self.parts.get(part)
        if f is None:
            f = self.parts[part] = _Failures(first=exc)
        f.count += 1
        f.last = f"{type(exc).__name__}: {exc}"
        now = self.clock()
        if f.logged_at is None:
            log.error("%s failed; it is isolated and counted, the service continues", part, exc_info=exc)
            f.logged_at = now
        elif now - f.logged_at >= self.period_s:
            log.error("%s: %d more failure(s) in the last %.0f s, latest %s", part, f.since_logged + 1, now - f.logged_at, f.last)
            f.logged_at, f.since_logged = now, 0
        else:
            f.since_logged += 1

    def first(self, prefix: str = "") -> BaseException | None:
        """The first exception of any part whose name starts with ``prefix``."""
        return next((f.first for name, f in self.parts.items() if name.startswith(prefix)), None)

    def report(self) -> dict[str, dict[str, Any]]:
        return {name: {"failures": f.count, "last": f.last} for name, f in sorted(self.parts.items())}


@dataclass
class _Sensor:
    total: int = 0
    since_report: int = 0
    last_arrival: float | None = None


@dataclass
class StatusTracker:
    """Counts arrivals per sensor; :meth:`snapshot` turns them into the status document."""

    clock: Callable[[], float] = time.monotonic
    sensors: dict[str, _Sensor] = field(default_factory=dict)
    events: dict[str, int] = field(default_factory=dict)  # runtime-level counters (camera busy, errors)

    def __post_init__(self) -> None:
        self._gps_noise_text: str | None = None  # the GPS noise check's verdict last logged
        self._last_wall = self.clock()
        self._last_cpu = time.process_time()
        self._logged_wait: str | None = None  # the visual-inertial start's last logged reason (logged on change)

    def saw(self, sensor: str, n: int = 1) -> None:
        s = self.sensors.get(sensor)
        if s is None:
            s = self.sensors[sensor] = _Sensor()
        s.total += n
        s.since_report += n
        s.last_arrival = self.clock()

    def count(self, event: str, n: int = 1) -> None:
        self.events[event] = self.events.get(event, 0) + n

    def snapshot(self, est: Estimator, fusion: FusionCore, extra: dict[str, Any] | None = None) -> dict[str, Any]:
        now, cpu = self.clock(), time.process_time()
        dt = max(now - self._last_wall, 1e-9)
        cpu_percent = 100.0 * (cpu - self._last_cpu) / dt
        self._last_wall, self._last_cpu = now, cpu
        sensors = {}
        for name, s in sorted(self.sensors.items()):
            sensors[name] = {
                "rate_hz": round(s.since_report / dt, 2),
                "age_s": None if s.last_arrival is None else round(now - s.last_arrival, 3),
                "total": s.total,
            }
            s.since_report = 0
        status = est.status()
        health = dict(status.health)
        rejected = {name: c["rejected"] for name, c in status.counts.items() if c["rejected"]}
        gps_noise = dict(status.gps_noise)
        if gps_noise["text"] != self._gps_noise_text:  # the log says it once, when it changes
            if gps_noise["text"] is not None:
                log.warning("%s: its fixes are weighed with the noise measured", gps_noise["text"])
            else:
                log.info("GPS claims believed again")
            self._gps_noise_text = gps_noise["text"]
        late = {name: c["rejected"] for name, c in fusion.counts_report().items() if c["rejected"]}
        doc = {
            "sensors": sensors,
            "initialized": status.initialised,
            "initialising": status.initialising,  # no running filter yet: nothing published, the start window fills
            "mode": status.mode.value,
            "heading": status.heading.value,
            "heading_aligned": status.heading_aligned,
            "local_frame": status.local_position,  # position (and an unknown heading) the filter's own
            "heading_sigma_deg": None if status.heading_sigma_deg is None else round(status.heading_sigma_deg, 3),
            "landmarks": status.landmarks,
            "rejected": rejected,
            "fusion": {
                "rejected": late,
                "buffered_imu": fusion.buffered_imu,
                "pending_measurements": fusion.pending_measurements,
                "lag_s": None if fusion.fused_until_ns is None or fusion.newest_imu_t_ns is None
                else round((fusion.newest_imu_t_ns - fusion.fused_until_ns) * 1e-9, 4),
            },
            "filter_resets": status.reset_counter,
            "health": health,
            "gps_noise": gps_noise,  # a GPS whose claimed sigma is not believed: the noise it really has
            "events": dict(self.events),
            "cpu_percent": round(cpu_percent, 1),
            "load_average": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
            "memory_mb": None if (rss := resident_memory_mb()) is None else round(rss, 1),
        }
        waiting = status.visual_start_waiting.as_dict() if status.visual_start_waiting is not None else None
        if waiting is not None:
            doc["visual_start"] = waiting
        offset = status.camera_time_offset_ms()
        if offset is not None:
            doc["camera_time_offset_ms"] = offset  # estimated beyond calibration.camera.time_offset_s
        mounting = status.camera_mounting_document()
        if mounting is not None:
            doc["camera_mounting"] = mounting  # the correction estimated beyond the configured camera R_BC, t_BC
        if (waiting and waiting["check"]) != self._logged_wait:
            if waiting is not None:
                log.info("visual-inertial start waiting: %s", waiting["text"])
            self._logged_wait = waiting and waiting["check"]
        if extra:
            doc.update(extra)
        return doc


class LatencyProbe:
    """Latencies [ns] of the last ``capacity`` published samples, for p50/p99 figures."""

    def __init__(self, capacity: int = 100_000) -> None:
        self._values = np.zeros(capacity, dtype=np.int64)
        self._n = 0

    def add(self, latency_ns: int) -> None:
        self._values[self._n % self._values.size] = latency_ns
        self._n += 1

    def __len__(self) -> int:
        return min(self._n, self._values.size)

    def percentiles_ms(self, *q: float) -> list[float]:
        values = self._values[: len(self)]
        if values.size == 0:
            return [float("nan")] * len(q)
        return [float(x) * 1e-6 for x in np.percentile(values, q)]
