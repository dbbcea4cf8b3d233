"""What the service may know of the estimator: one frozen snapshot, and typed events.

The runtime, the replay report and the benches read the estimator only through
:meth:`~vtolpose.estimator.filter.Estimator.status` (an :class:`EstimatorStatus`), never its
attributes: the estimator's insides can change without breaking them, and nothing they hold can
change the estimator. Events carry their kind and figures as fields, so nobody parses text.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum
from types import MappingProxyType
from typing import Mapping

from vtolpose.estimator.init.visual_inertial import VisualStartProgress
from vtolpose.estimator.modes import FilterMode, HeadingMode, heading_aligned


class EventKind(Enum):
    INITIALISING = "initialising"  # moving at the start, camera only: no state until the visual-inertial start
    STARTED = "started"  # a running filter from a complete start (IMU window, GPS, or the visual-inertial window)
    POSITION_INITIALISED = "position_initialised"  # the position placed at a fix
    GPS_JOINED = "gps_joined"  # a GPS joined a filter without a world frame
    HEADING_PLACED = "heading_placed"  # the heading hypotheses placed the heading
    RESET = "reset"  # reset_counter stepped: see ``reset_kind``
    GPS_NOISE = "gps_noise"  # the GPS's claimed accuracy believed, or no longer, from its fixes' own scatter


@dataclass(frozen=True, slots=True)
class EstimatorEvent:
    """One event: when, what, the reset counter after it, its figures, and a sentence for people."""

    t_ns: int
    kind: EventKind
    message: str
    reset_counter: int
    reset_kind: str | None = None  # for RESET: imu_gap, state_invalid, gps_rejected, camera_lost
    figures: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))


@dataclass(frozen=True, slots=True)
class HeadingPlacement:
    """How the heading hypotheses placed the heading."""

    t_ns: int
    heading_deg: float
    sigma_deg: float
    fixes: int
    hypotheses: int
    best_weight: float


@dataclass(frozen=True, slots=True)
class EstimatorStatus:
    """A snapshot: the modes, the flags read off them, the published heading's sigma, counters, health."""

    t_ns: int | None  # the filter state's time; None before the start
    mode: FilterMode
    heading: HeadingMode
    reset_counter: int
    heading_sigma_deg: float | None  # of the published heading (a heading anywhere on the circle while unknown)
    heading_placement: HeadingPlacement | None
    started_moving: bool
    counts: Mapping[str, Mapping]  # per sensor: received, used, rejected by reason, flagged
    health: Mapping  # estimator.health's report at t_ns
    events: tuple[EstimatorEvent, ...]
    gyro_bias: tuple[float, float, float] | None
    accel_bias: tuple[float, float, float] | None
    landmarks: int  # in the map now
    landmarks_initialised: int  # over the run
    landmarks_deleted: Mapping[str, int]  # over the run, by reason
    visual_start_waiting: VisualStartProgress | None = None  # why the visual-inertial start has not come yet
    visual_start_history: tuple[VisualStartProgress, ...] = ()  # each change of the check that held it
    visual_start_attempts: int = 0
    gps_noise: Mapping = field(default_factory=lambda: MappingProxyType({}))  # the GPS noise check's verdict
    # The camera's residual time offset beyond the configured one, estimated online: (estimate, sigma) in
    # seconds (a frame stamped t was taken at t + estimate); None unless estimated and the camera used.
    camera_time_offset_s: tuple[float, float] | None = None
    # The camera's mounting correction beyond the configured R_BC, t_BC, estimated online (vision.mounting): the
    # estimate [φ (rad, body axes: R_BC = Exp(φ) R_BC⁰), c (m, t_BC = t_BC⁰ + c)] and its six sigmas; None unless
    # estimated and the camera used.
    camera_mounting: tuple[tuple[float, ...], tuple[float, ...]] | None = None

    @property
    def initialised(self) -> bool:
        return self.mode.initialised

    @property
    def initialising(self) -> bool:
        """No pose yet: before the start (the IMU's window or the visual-inertial one filling)."""
        return not self.mode.initialised

    @property
    def local_position(self) -> bool:
        return self.mode.local_position

    @property
    def position_initialized(self) -> bool:
        return self.mode.position_from_gps

    @property
    def heading_aligned(self) -> bool:
        return heading_aligned(self.mode, self.heading)

    @property
    def heading_source(self) -> str:
        """Where the heading came from, in words."""
        if self.heading_placement is not None:
            return "heading bank"
        if self.heading_aligned:
            return "known"
        return "own frame (visual-inertial start)" if self.local_position else "unknown"

    def camera_time_offset_ms(self) -> dict[str, float] | None:
        """The estimated residual camera time offset and its sigma in ms, rounded for documents; None unless estimated."""
        if self.camera_time_offset_s is None:
            return None
        value, sigma = self.camera_time_offset_s
        return {"estimate": round(value * 1e3, 3), "sigma": round(sigma * 1e3, 3)}

    def camera_mounting_document(self) -> dict[str, dict[str, list[float]]] | None:
        """The estimated mounting correction and its sigmas, rotation in degrees and translation in mm, rounded for
        documents; None unless estimated."""
        if self.camera_mounting is None:
            return None
        value, sigma = self.camera_mounting
        deg, mm = 180.0 / math.pi, 1e3
        return {
            "rotation_deg": {"estimate": [round(x * deg, 3) for x in value[0:3]], "sigma": [round(x * deg, 3) for x in sigma[0:3]]},
            "translation_mm": {"estimate": [round(x * mm, 2) for x in value[3:6]], "sigma": [round(x * mm, 2) for x in sigma[3:6]]},
        }

    def first(self, kind: EventKind) -> EstimatorEvent | None:
        """The first event of ``kind``, if any."""
        return next((e for e in self.events if e.kind is kind), None)
