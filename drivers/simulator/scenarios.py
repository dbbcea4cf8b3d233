"""The simulated worlds: a motion, a ground to look at, and the GPS receiver that goes with them.

- ``book``: the thesis' rig. A robot arm waves the sensor platform 0.5–1 m above a table with
  a book on it; tens of centimetres of motion, tilts up to ~12°, yaw swings of ~±30°.
- ``landfill``: a helicopter stands on its pad, climbs to 45 m and flies a lawnmower survey at
  8 m/s over rolling ground with mounds, back and forth over its lanes for as long as asked.

Each scenario starts with a static stretch (the estimator levels itself and measures the gyro
bias from it) and offers ``ground_height(n, e)``: the down coordinate [m] of the ground, so a
renderer can later lay a textured height field under the trajectory.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterator, Protocol

import numpy as np

from vtolpose.drivers.simulator.gps_model import GpsErrorModel
from vtolpose.drivers.simulator.trajectory import (
    AlongTrack,
    EulerTrajectory,
    Hold,
    Segment,
    SegmentPath,
    SineMotion,
    SmoothMove,
    ThrustAlignedTrajectory,
    Trajectory,
    Turn,
    turn_sidestep,
)


class Scenario(Protocol):
    name: str
    description: str
    static_s: float
    origin_lla: tuple[float, float, float] | None
    heading_sigma_deg: float  # accuracy of the initial heading the crew states
    in_flight_s: float  # where a flight that starts in the air (``--start-in-flight``) joins the trajectory

    def ground_height(self, n: np.ndarray, e: np.ndarray) -> np.ndarray: ...

    def trajectory(self, duration_s: float, gravity: float) -> Trajectory: ...

    def gps_model(self) -> GpsErrorModel: ...


def _sines(rows: list[list[tuple[float, float, float]]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(amplitude, angular frequency, phase) per axis → three (3, K) arrays."""
    table = np.array(rows, dtype=float)
    return table[..., 0], table[..., 1], table[..., 2]


# Arm motion: incommensurate frequencies so the pattern never repeats exactly.
_BOOK_POSITION = _sines(
    [
        [(0.25, 1.70, 0.0), (0.08, 3.30, 1.0)],
        [(0.22, 1.90, 0.5), (0.07, 3.70, 2.0)],
        [(0.10, 1.10, 1.2), (0.03, 2.50, 0.3)],
    ]
)
_BOOK_ATTITUDE = _sines(
    [
        [(0.14, 0.70, 0.4), (0.05, 1.60, 1.1)],
        [(0.13, 0.60, 2.1), (0.04, 1.80, 0.2)],
        [(0.42, 0.35, 0.0), (0.10, 0.95, 0.5)],
    ]
)


@dataclass(frozen=True, slots=True)
class BookScenario:
    """The sensor platform on a robot arm above a table (surface at down = 0) with a book."""

    name: str = "book"
    description: str = "robot arm waving the sensor platform 0.5-1 m above a book on a table"
    static_s: float = 10.0  # the thesis calibrates on the spot before each run (section 5.2)
    ramp_s: float = 4.0
    centre_ned: tuple[float, float, float] = (0.0, 0.0, -0.75)
    centre_euler: tuple[float, float, float] = (0.03, -0.04, 0.35)
    table_half_size: tuple[float, float] = (1.0, 0.7)
    book_half_size: tuple[float, float] = (0.12, 0.085)
    book_thickness: float = 0.035
    book_yaw_rad: float = 0.25
    floor_depth: float = 0.75
    gps_sigma_h: float = 0.02
    origin_lla: tuple[float, float, float] | None = None
    heading_sigma_deg: float = 0.3  # the robot's base frame is surveyed
    in_flight_s: float = 20.0  # the arm waving at full amplitude

    def ground_height(self, n: np.ndarray, e: np.ndarray) -> np.ndarray:
        """Table top at 0, the book's cover at ``-thickness``, the floor beyond the table."""
        n, e = np.broadcast_arrays(np.asarray(n, dtype=float), np.asarray(e, dtype=float))
        c, s = np.cos(self.book_yaw_rad), np.sin(self.book_yaw_rad)
        along, across = c * n + s * e, -s * n + c * e
        on_book = (np.abs(along) <= self.book_half_size[0]) & (np.abs(across) <= self.book_half_size[1])
        on_table = (np.abs(n) <= self.table_half_size[0]) & (np.abs(e) <= self.table_half_size[1])
        return np.where(on_book, -self.book_thickness, np.where(on_table, 0.0, self.floor_depth))

    def trajectory(self, duration_s: float, gravity: float) -> Trajectory:
        """Endless; ``duration_s`` and ``gravity`` do not matter to an arm."""
        position = SineMotion(np.array(self.centre_ned), *_BOOK_POSITION, self.static_s, self.ramp_s)
        attitude = SineMotion(np.array(self.centre_euler), *_BOOK_ATTITUDE, self.static_s, self.ramp_s)
        return EulerTrajectory(position, attitude)

    def gps_model(self) -> GpsErrorModel:
        return GpsErrorModel(sigma_h=self.gps_sigma_h)


# Landfill mounds: (north, east, height, radius) in metres, over the survey area.
_MOUNDS = np.array(
    [
        [120.0, 40.0, 9.0, 40.0],
        [250.0, 120.0, 12.0, 50.0],
        [170.0, 230.0, 7.0, 35.0],
        [330.0, 250.0, 10.0, 45.0],
        [60.0, 170.0, 5.0, 30.0],
    ]
)


@dataclass(frozen=True, slots=True)
class LandfillScenario:
    """A helicopter surveying a landfill near Linköping (origin on the pad, on the ground)."""

    name: str = "landfill"
    description: str = "helicopter: static on the pad, climb out to 45 m, lawnmower survey at 8 m/s over a landfill"
    static_s: float = 10.0  # the thesis calibrates on the spot before each run (section 5.2)
    imu_height_on_ground: float = 0.8
    climb_s: float = 20.0
    climb_out_m: float = 40.0  # a helicopter climbs out along its track, not straight up
    altitude: float = 45.0
    accelerate_s: float = 8.0
    speed: float = 8.0
    leg_length: float = 300.0
    lane_spacing: float = 60.0
    lanes: int = 5
    leg_heading_rad: float = float(np.deg2rad(20.0))
    gps_sigma_h: float = 1.0
    gps_lever_arm_b: tuple[float, float, float] = (0.0, 0.0, -0.3)
    origin_lla: tuple[float, float, float] | None = (58.43, 15.68, 60.0)
    heading_sigma_deg: float = 0.5  # lined up with the surveyed pad axis (no magnetometer on board)
    in_flight_s: float = 70.0  # on the first survey leg at 8 m/s, 45 m up, 5 s before the turn to the next lane

    def __post_init__(self) -> None:
        if self.lanes < 2:
            raise ValueError(f"landfill survey needs at least 2 lanes, got {self.lanes}")
        for name in ("climb_s", "altitude", "accelerate_s", "speed", "leg_length", "lane_spacing"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"landfill {name} must be positive, got {getattr(self, name)}")

    def _terrain_up(self, n: np.ndarray, e: np.ndarray) -> np.ndarray:
        rolling = 3.0 * np.sin(2 * np.pi * n / 260.0 + 0.5) * np.sin(2 * np.pi * e / 190.0 + 1.1)
        slope = 0.01 * n - 0.006 * e
        mounds = sum(h * np.exp(-((n - mn) ** 2 + (e - me) ** 2) / (2 * r**2)) for mn, me, h, r in _MOUNDS)
        return rolling + slope + mounds

    def ground_height(self, n: np.ndarray, e: np.ndarray) -> np.ndarray:
        """Rolling ground with mounds; down = 0 on the pad at the origin."""
        n, e = np.asarray(n, dtype=float), np.asarray(e, dtype=float)
        return self._terrain_up(np.zeros(()), np.zeros(())) - self._terrain_up(n, e)

    def _lane_sequence(self) -> Iterator[int]:
        """Lane indices forever: 0, 1, ..., lanes-1, lanes-2, ..., 0, 1, ..."""
        lane, step = 0, 1
        while True:
            yield lane
            if not 0 <= lane + step < self.lanes:
                step = -step
            lane += step

    def _path(self, duration_s: float) -> SegmentPath:
        pad = np.array([0.0, 0.0, -self.imu_height_on_ground])
        heading = self.leg_heading_rad
        segments: list[Segment] = [
            Hold("static", self.static_s, pad, heading),
            SmoothMove(
                "climb",
                self.climb_s,
                pad,
                heading,
                np.array([self.climb_out_m * np.cos(heading), self.climb_out_m * np.sin(heading), -self.altitude - pad[2]]),
            ),
        ]
        segments.append(AlongTrack("accelerate", self.accelerate_s, *segments[-1].end(), 0.0, self.speed))
        leg_s = self.leg_length / self.speed
        turn_s = self.lane_spacing / (self.speed * turn_sidestep(np.pi))
        right = np.array([-np.sin(heading), np.cos(heading)])
        lanes = self._lane_sequence()
        lane = next(lanes)
        total_s = sum(s.duration_s for s in segments)
        while total_s < duration_s:
            segments.append(AlongTrack("leg", leg_s, *segments[-1].end(), self.speed, self.speed))
            start, track = segments[-1].end()
            next_lane = next(lanes)
            sideways = (next_lane - lane) * right
            # Turn towards the next lane: the sign of (track direction × sideways) about down.
            direction = np.sign(np.cos(track) * sideways[1] - np.sin(track) * sideways[0])
            segments.append(Turn("turn", turn_s, start, track, self.speed, float(direction * np.pi)))
            lane = next_lane
            total_s += leg_s + turn_s
        return SegmentPath(tuple(segments))

    def trajectory(self, duration_s: float, gravity: float) -> Trajectory:
        """Flight covering at least ``duration_s``; the survey repeats over its lanes."""
        return ThrustAlignedTrajectory(self._path(duration_s), gravity)

    def gps_model(self) -> GpsErrorModel:
        return GpsErrorModel(sigma_h=self.gps_sigma_h, lever_arm_b=self.gps_lever_arm_b)


SCENARIOS: dict[str, Callable[[], Scenario]] = {"book": BookScenario, "landfill": LandfillScenario}


def make_scenario(name: str) -> Scenario:
    """The scenario called ``name``; a clear error lists the known ones."""
    try:
        return SCENARIOS[name]()
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; choose one of {sorted(SCENARIOS)}") from None
