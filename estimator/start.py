"""Starting the filter: what comes before a running state, in one place, handing the filter a complete start.

As OpenVINS's initialiser hands its filter a whole state, the coordinator hands :class:`Start` values:
the filter only adopts them. Three kinds:

- from the IMU's window (``inertial/initializer.py``): still, or moving when the window is not still,
  when the GPS heard meanwhile moves (steady flight feels still to an IMU) or when the camera sees the
  scene move; the fixes of the last second give a moving start its velocity, the last fix places a
  still one. Moving with a camera and no GPS there is no start from the IMU: the filter waits,
  *initialising*, for the visual window, or for a second of fixes and then takes the IMU's latest window;
- from a converged visual-inertial window (``init/visual_inertial.py``): the robot, the landmarks and
  their joint covariance;
- a GPS joining a filter that has no world frame (:meth:`StartCoordinator.join`): the velocity fitted to
  its first second of fixes.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from vtolpose.estimator.core import covariance
from vtolpose.estimator.core.covariance import BG, V
from vtolpose.estimator.core.kalman import chi2_gate
from vtolpose.estimator.core.measurements import GpsFix
from vtolpose.estimator.core.rotation import yaw_of
from vtolpose.estimator.core.state import CalibrationLayout, FilterState, StateLayout
from vtolpose.estimator.inertial.initializer import InitialAttitude, InitOptions, StaticInitializer
from vtolpose.estimator.inertial.startup import (
    mean_acceleration_from_fixes, state_from_static, tilt_sigma_of_mean_acceleration, velocity_from_fixes,
)
from vtolpose.estimator.init.visual_inertial import ROBOT_DIM as VI_ROBOT_DIM
from vtolpose.estimator.init.visual_inertial import Gauge, VisualInertialInitializer, VisualInertialStart
from vtolpose.estimator.modes import ModeEvent
from vtolpose.estimator.vision.landmarks import INVERSE_DEPTH

VELOCITY_FIT_S = 1.0  # the fixes before the start that give its velocity (a constant acceleration holds that long)
MAX_FIXES_HELD = 64  # the GPS heard while the IMU window fills (or while a GPS joins): a bounded queue


@dataclass(frozen=True, slots=True)
class Start:
    """A complete first state and what the filter needs to adopt it."""

    state: FilterState
    gravity: float
    message: str
    event: ModeEvent  # the mode transition the start is
    moving: bool  # an IMU start that no still window began (the camera then waits for the heading hypotheses)
    fixed_bias_var: np.ndarray  # the thesis model's gyro-bias variance
    place_at: GpsFix | None = None  # a still start's position comes from this fix
    descriptors: np.ndarray | None = None  # a visual start's landmarks' descriptors
    landmark_sigmas: np.ndarray | None = None  # and their inverse depths' sigmas


@dataclass(frozen=True, slots=True)
class Join:
    """A GPS's first second of fixes, for a filter without a world frame: the velocity they give (None when
    too few for a fit) and how many gave it."""

    velocity: tuple[np.ndarray, np.ndarray] | None
    fixes_used: int


class StartCoordinator:
    """The IMU window, the fixes heard before the start, the camera's motion cue and the visual window."""

    def __init__(self, layout: StateLayout, init: InitOptions, gravity: float, heading_rad: float | None,
                 heading_sigma: float, gps_sigma_floor_m: float,
                 visual_inertial: VisualInertialInitializer | None) -> None:
        self.layout = layout
        self.init = init
        self.gravity = gravity
        self.heading_known = heading_rad is not None
        self.heading_sigma = heading_sigma
        self.gps_sigma_floor_m = gps_sigma_floor_m
        self.initializer = StaticInitializer(init, gravity, heading_rad or 0.0)
        self.visual_inertial = visual_inertial
        self.fixes: deque[GpsFix] = deque(maxlen=MAX_FIXES_HELD)
        self._held_gauge: tuple[np.ndarray, float] | None = None  # where a dropped filter was lost


    def hear(self, fix: GpsFix) -> None:
        """A usable fix before the start."""
        self.fixes.append(fix)

    def heard_for(self, seconds: float) -> bool:
        """Whether the fixes held span ``seconds``."""
        return len(self.fixes) > 1 and (self.fixes[-1].t_ns - self.fixes[0].t_ns) * 1e-9 >= seconds

    def reweigh(self, weigh: Callable[[GpsFix], GpsFix]) -> None:
        """The fixes heard so far, each with the sigma ``weigh`` gives it (the GPS's claimed accuracy not believed)."""
        self.fixes = deque(map(weigh, self.fixes), maxlen=MAX_FIXES_HELD)

    def from_imu(self, init: InitialAttitude, camera_received: bool, gps_heard: bool) -> Start:
        """The start the IMU's window gives, with the GPS heard meanwhile. A window that looks still to the IMU is
        also what steady straight flight (or a steady turn) looks like: if the fixes say the vehicle moves, or
        the camera saw the scene move, it is no still start."""
        window = [f for f in self.fixes if init.t_ns - f.t_ns < VELOCITY_FIT_S * 1e9]
        spread = self._fixes_moved(init.t_ns)
        velocity = velocity_from_fixes(window, init.t_ns, self.gps_sigma_floor_m)
        moving = spread or (velocity is not None
                            and chi2_gate(3, 0.999) < float(velocity[0] @ np.linalg.solve(velocity[1], velocity[0])))
        seen = self.visual_inertial is not None and self.visual_inertial.image_moving(init.t_ns)
        if init.static and (moving or seen):
            init = self.initializer.as_moving(init)
        if not init.static:
            init = self._tilt_from_measured_acceleration(init)
        self.fixes.clear()
        heading_sigma = math.hypot(self.heading_sigma, init.heading_drift_sigma) if self.heading_known else 0.0
        state = state_from_static(self.layout, init, self.init, heading_sigma)
        if velocity is not None and not init.static:
            state.v = velocity[0]
            covariance.reinitialise(state.cov, V, velocity[1])
        how = ("still" if init.static else "moving (GPS)" if moving else "moving (camera), from the mean specific force" if seen
               else f"not still within {self.init.max_wait_s:g} s: from the mean specific force")
        placed = init.static and window and (init.t_ns - window[-1].t_ns) < 1e9  # the last fix places a still vehicle
        if not init.static and not gps_heard and self.visual_inertial is not None and camera_received:
            event = ModeEvent.START_BLIND
            how += "; no state until the visual-inertial start"
        else:
            event = ModeEvent.START_PLACED if placed else ModeEvent.START_UNREFERENCED
        return Start(state, init.gravity, f"started from {init.n_samples} IMU samples, {how}; g = {init.gravity:.4f} m/s^2",
                     event, not init.static, np.full(3, init.sigma_gyro_bias**2), window[-1] if placed else None)

    def _tilt_from_measured_acceleration(self, init: InitialAttitude) -> InitialAttitude:
        """A moving start's tilt is the direction of its window's mean specific force, off by the window's mean
        acceleration: where the fixes over the window measure it, that sets the tilt's sigma (the configured
        guess where they cannot)."""
        t0_ns = init.t_ns - round(init.window_s * 1e9)
        measured = mean_acceleration_from_fixes(self.fixes, t0_ns, init.t_ns, VELOCITY_FIT_S, self.gps_sigma_floor_m)
        if measured is None:
            return init
        return init.with_mean_acceleration(tilt_sigma_of_mean_acceleration(*measured, init.gravity))

    def _fixes_moved(self, t_ns: int) -> bool:
        """The fixes over the IMU's window lie further apart than their noise allows (5 σ): a cruise that a
        noisy GPS's one-second velocity fit cannot tell from rest (1 m fixes, 8 m/s)."""
        window_ns = int(self.init.static_window_s * 1e9)
        fixes = [f for f in self.fixes if t_ns - f.t_ns <= window_ns]
        if len(fixes) < 2:
            return False
        first, last = fixes[0], fixes[-1]
        moved = float(np.linalg.norm((np.asarray(last.p_ned) - np.asarray(first.p_ned))[:2]))
        return moved > 5.0 * math.hypot(first.sigma_h, last.sigma_h)

    def hold_gauge(self, state: FilterState) -> None:
        """A running filter is dropped (the camera lost in its own frame): the visual start that follows
        takes its position and heading where it was lost, so the frame goes on."""
        self._held_gauge = (state.p.copy(), yaw_of(state.q))

    def gauge(self) -> Gauge:
        """What a visual-inertial start cannot observe: where a dropped filter was lost, or the origin and the
        known heading (zero when unknown), carried by the gyro from the first sample to the latest."""
        if self._held_gauge is not None:
            p, heading = self._held_gauge
            return Gauge(p.copy(), heading, self.heading_sigma if self.heading_known else None)
        if not self.heading_known:
            return Gauge(np.zeros(3), 0.0, None)
        heading, drift = self.initializer.stated_heading_now()
        return Gauge(np.zeros(3), heading, math.hypot(self.heading_sigma, drift))

    def from_window(self, start: VisualInertialStart) -> Start:
        """The start a converged visual-inertial window gives, its landmarks included."""
        state = FilterState(self.layout)
        state.t_ns = start.t_ns
        state.p, state.v, state.q, state.b_g = start.p.copy(), start.v.copy(), start.q.copy(), start.b_g.copy()
        if self.layout.estimates_biases:
            state.b_a = start.b_a.copy()
        state.landmarks = start.landmarks.copy()
        calib = 0 if start.time_offset_s is None else 1  # the window solved the camera's time offset: its state
        if calib:
            state.calib, state.calib_layout = np.array([start.time_offset_s]), CalibrationLayout(time_offset=True)
        state.cov = covariance.robot_and_map(start.cov, VI_ROBOT_DIM, self.layout.robot_dim)
        return Start(state, self.gravity, start.describe(), ModeEvent.VISUAL_START, True,
                     covariance.block_variances(start.cov, BG), None, start.descriptors,
                     covariance.landmark_sigmas(start.cov, VI_ROBOT_DIM + calib, INVERSE_DEPTH))

    def join(self, fix: GpsFix) -> Join | None:
        """A fix of a GPS joining a filter without a world frame: None while its first ``VELOCITY_FIT_S`` of
        fixes is collected, then the velocity they give (the last one's second preferred)."""
        self.fixes.append(fix)
        if (fix.t_ns - self.fixes[0].t_ns) * 1e-9 < VELOCITY_FIT_S:
            return None
        fixes = list(self.fixes)
        self.fixes.clear()
        floor = self.gps_sigma_floor_m
        recent = [f for f in fixes if fix.t_ns - f.t_ns <= VELOCITY_FIT_S * 1e9]
        velocity = velocity_from_fixes(recent, fix.t_ns, floor) or velocity_from_fixes(fixes, fix.t_ns, floor)
        return Join(velocity, len(recent if velocity is not None else fixes))
