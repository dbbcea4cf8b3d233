"""Named motions for the camera test matrix: a hover, a gentle hand-held sweep, an aggressive one.

Each is an :class:`EulerTrajectory` of incommensurate sinusoids (closed-form derivatives, so the
IMU is the exact derivative of the truth) about a centre pose, plus, for the hover, the rotor
vibration its IMU feels. Bands, measured over the moving part (``tests/test_floor_matrix.py``):

- ``hover``: centimetre wander, sub-degree wobble; acceleration RMS < 0.05 m/s² in the truth,
  rotor vibration on the IMU (77 Hz, 0.6 m/s² and 0.03 rad/s RMS per axis).
- ``gentle``: a hand-held sweep, 0.1–0.15 m/s² RMS, slow turns (≲ 0.2 rad/s).
- ``aggressive``: ≈ 2 m/s² RMS, turns peaking near 1 rad/s.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from vtolpose.drivers.simulator.imu_model import ImuErrorModel
from vtolpose.drivers.simulator.trajectory import EulerTrajectory, SineMotion

Sines = tuple[tuple[tuple[float, float, float], ...], ...]  # per axis: (amplitude, angular frequency, phase) terms


@dataclass(frozen=True, slots=True)
class Vibration:
    rotor_hz: float
    accel_rms: float
    gyro_rms: float


@dataclass(frozen=True, slots=True)
class MotionProfile:
    name: str
    description: str
    position: Sines  # metres about the centre, NED
    attitude: Sines  # radians about the centre's Z-Y-X Euler angles
    vibration: Vibration | None = None

    def trajectory(self, centre_ned: np.ndarray, centre_euler: np.ndarray, start_s: float, ramp_s: float) -> EulerTrajectory:
        """The motion about the centre pose, ramping in over ``ramp_s`` from ``start_s`` (may be negative:
        already moving at t = 0)."""
        def motion(centre: np.ndarray, sines: Sines) -> SineMotion:
            table = np.array(sines, dtype=float)
            return SineMotion(np.asarray(centre, dtype=float), table[..., 0], table[..., 1], table[..., 2], start_s, ramp_s)

        return EulerTrajectory(motion(centre_ned, self.position), motion(centre_euler, self.attitude))

    def imu_model(self, base: ImuErrorModel | None = None) -> ImuErrorModel:
        """``base`` (default: the simulator's IMU) with this motion's vibration added."""
        base = base or ImuErrorModel()
        if self.vibration is None:
            return base
        v = self.vibration
        return replace(base, vibration_hz=v.rotor_hz, vibration_accel_rms=v.accel_rms, vibration_gyro_rms=v.gyro_rms)


HOVER = MotionProfile(
    "hover", "near-still hover with rotor vibration",
    position=(((0.012, 1.3, 0.0), (0.002, 3.1, 1.0)), ((0.010, 1.1, 0.5), (0.002, 2.7, 2.0)),
              ((0.006, 1.7, 1.2), (0.001, 3.7, 0.3))),
    attitude=(((0.006, 1.5, 0.4), (0.002, 4.1, 1.1)), ((0.006, 1.3, 2.1), (0.002, 3.9, 0.2)),
              ((0.010, 0.4, 0.0), (0.003, 1.9, 0.5))),
    vibration=Vibration(rotor_hz=77.0, accel_rms=0.6, gyro_rms=0.03),
)
GENTLE = MotionProfile(
    "gentle", "hand-held sweep: about 0.12 m/s² RMS, slow turns",
    position=(((0.28, 0.55, 0.0), (0.035, 1.45, 1.0)), ((0.24, 0.65, 0.5), (0.03, 1.30, 2.0)),
              ((0.05, 0.85, 1.2), (0.012, 1.70, 0.3))),
    attitude=(((0.06, 0.50, 0.4), (0.02, 1.10, 1.1)), ((0.05, 0.45, 2.1), (0.02, 1.20, 0.2)),
              ((0.30, 0.30, 0.0), (0.05, 0.80, 0.5))),
)
AGGRESSIVE = MotionProfile(
    "aggressive", "aggressive sweep: about 2 m/s² RMS, turns near 1 rad/s",
    position=(((0.28, 2.2, 0.0), (0.07, 4.3, 1.0)), ((0.26, 2.5, 0.5), (0.06, 3.9, 2.0)),
              ((0.07, 2.9, 1.2), (0.025, 5.1, 0.3))),
    attitude=(((0.20, 2.0, 0.4), (0.05, 4.5, 1.1)), ((0.18, 2.3, 2.1), (0.04, 4.1, 0.2)),
              ((0.32, 1.6, 0.0), (0.07, 3.3, 0.5))),
)
PROFILES: dict[str, MotionProfile] = {p.name: p for p in (HOVER, GENTLE, AGGRESSIVE)}
