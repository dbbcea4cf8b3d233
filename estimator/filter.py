"""The estimator: initialisation, IMU propagation and measurement updates, in time order.

Feed it samples in timestamp order (``estimator.fusion`` does the ordering for late
measurements); ask it for the pose. Bad samples are counted per sensor and reason, never
raised: the caller gets the best estimate the good data allow.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from estimator.calibration import Calibration, ImuNoise
from estimator.gps_update import GpsUpdater, gps_sigmas
from estimator.heading import AlignOptions, HeadingAligner, HeadingSolution
from estimator.initializer import InitOptions, StaticInitializer
from estimator.kalman import UpdateOutcome
from estimator.measurements import GpsFix, RejectionCounts
from estimator.propagator import ImuPropagator
from estimator.rotation import quat_exp, quat_mul
from estimator.state import FilterState, StateLayout

HEADING_SOURCES = ("auto", "dataset", "gps")


@dataclass(slots=True)
class FilterOptions:
    variant: str = "biases"
    heading_source: str = "auto"  # auto: the dataset's known heading if any, else align from GPS
    heading_deg: float | None = None  # an operator-entered heading overrides both
    gps_gate: float | None = 7.81  # χ², 3 dof, 95 % (spec); None disables the gate
    gps_sigma_floor_m: float = 0.005
    max_imu_gap_s: float = 0.1
    noise: ImuNoise | None = None  # overrides the calibration's noise when given
    init: InitOptions = field(default_factory=InitOptions)
    align: AlignOptions = field(default_factory=AlignOptions)

    def __post_init__(self) -> None:
        StateLayout(self.variant)  # validates the variant name
        if self.heading_source not in HEADING_SOURCES:
            raise ValueError(f"heading_source must be one of {', '.join(HEADING_SOURCES)}, got {self.heading_source!r}")


@dataclass(frozen=True, slots=True)
class PoseEstimate:
    """What the outputs publish: pose, rates and uncertainty at ``t_ns``."""

    t_ns: int
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    omega_b: np.ndarray
    pose_cov: np.ndarray  # 6 × 6, [δp, δθ] (world-frame attitude error)
    vel_cov: np.ndarray  # 3 × 3, world-frame velocity
    heading_aligned: bool
    reset_counter: int


class Estimator:
    def __init__(self, calibration: Calibration, options: FilterOptions | None = None) -> None:
        self.options = options or FilterOptions()
        self.calibration = calibration
        self.layout = StateLayout(self.options.variant)
        self.noise = self.options.noise or calibration.imu.noise
        self.gps = GpsUpdater(calibration.gps.lever_arm_b, self.options.gps_gate, self.options.gps_sigma_floor_m)
        self.counts = {"imu": RejectionCounts(), "gps": RejectionCounts()}
        self.state: FilterState | None = None
        self.propagator: ImuPropagator | None = None
        self.heading_aligned = False
        self.heading_solution: HeadingSolution | None = None
        self.position_initialized = False
        self.reset_counter = 0
        self.events: list[tuple[int, str]] = []  # (t_ns, message): initialisation, alignment, resets
        heading = self._known_heading()
        self._initializer = StaticInitializer(self.options.init, calibration.imu.gravity, heading or 0.0)
        self._heading_known = heading is not None
        self._aligner = HeadingAligner(self.options.align)
        self._last_imu_t: int | None = None
        self._gyro = np.zeros(3)
        self._accel = np.zeros(3)
        self._pending_fix: GpsFix | None = None

    # ----------------------------------------------------------------------------- status
    @property
    def initialized(self) -> bool:
        return self.state is not None

    def _known_heading(self) -> float | None:
        opts = self.options
        if opts.heading_deg is not None:
            return math.radians(opts.heading_deg)
        if opts.heading_source == "gps":
            return None
        if opts.heading_source == "dataset" and self.calibration.initial_heading_rad is None:
            raise ValueError("heading_source 'dataset' but the dataset gives no initial heading")
        return self.calibration.initial_heading_rad

    # -------------------------------------------------------------------------------- IMU
    def process_imu(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray) -> bool:
        """Propagate to ``t_ns``. Returns False when the sample was rejected (and counted)."""
        counts = self.counts["imu"]
        counts.received += 1
        # One dot product is finite exactly when every component is (cheaper than isfinite).
        if not math.isfinite(float(gyro @ gyro + accel @ accel)):
            counts.reject("non_finite")
            return False
        if self._last_imu_t is not None and t_ns <= self._last_imu_t:
            counts.reject("time_not_increasing")
            return False
        counts.used += 1
        if self.state is None:
            self._last_imu_t = t_ns
            init = self._initializer.add(t_ns, gyro, accel)
            if init is not None:
                self._start(init)
            self._gyro, self._accel = gyro, accel
            return True
        gap_s = (t_ns - self._last_imu_t) * 1e-9
        if gap_s > self.options.max_imu_gap_s:
            counts.flag("gap_bridged")  # still propagated, with the covariance growing over the gap
        self._last_imu_t = t_ns
        self._propagate_to(t_ns, 0.5 * (self._gyro + gyro), 0.5 * (self._accel + accel))
        self._gyro, self._accel = gyro, accel
        return True

    def _propagate_to(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray) -> None:
        state = self.state
        dt = (t_ns - state.t_ns) * 1e-9
        if dt <= 0.0:
            return
        extra = 0.0 if self.heading_aligned else self.options.align.unaligned_accel_noise
        a_w = self.propagator.propagate(state, gyro, accel, dt, extra)
        state.t_ns = t_ns
        if not self.heading_aligned:
            self._aligner.on_imu(dt, a_w[:2])

    def _start(self, init) -> None:
        opts = self.options.init
        state = FilterState(self.layout)
        state.t_ns = init.t_ns
        state.q = init.q
        state.b_g = init.gyro_bias.copy()
        n = self.layout.robot_dim
        cov = np.zeros((n, n))
        sigma_v = opts.sigma_velocity_static if init.static else opts.sigma_velocity_moving
        cov[0:3, 0:3] = np.eye(3) * 0.01**2
        cov[3:6, 3:6] = np.eye(3) * sigma_v**2
        sigma_yaw = math.radians(opts.sigma_heading_known_deg) if self._heading_known else math.pi
        cov[6:9, 6:9] = np.diag([init.sigma_roll_pitch**2, init.sigma_roll_pitch**2, sigma_yaw**2])
        if self.layout.estimates_biases:
            cov[9:12, 9:12] = np.eye(3) * init.sigma_gyro_bias**2
            cov[12:15, 12:15] = np.eye(3) * opts.sigma_accel_bias**2
        state.cov = cov
        self.state = state
        self.propagator = ImuPropagator(self.noise, init.gravity)
        self.heading_aligned = self._heading_known
        how = "static" if init.static else "moving (no static window)"
        self.events.append((init.t_ns, f"initialised attitude from {init.n_samples} IMU samples, {how}; g = {init.gravity:.4f} m/s^2"))
        if self._pending_fix is not None and (init.t_ns - self._pending_fix.t_ns) < 1e9:
            self._init_position(self._pending_fix)
        self._pending_fix = None

    # -------------------------------------------------------------------------------- GPS
    def process_gps(self, fix: GpsFix) -> UpdateOutcome | None:
        """Fuse a fix at its own time. Returns the update outcome, or None if it was not fused."""
        counts = self.counts["gps"]
        counts.received += 1
        p = np.asarray(fix.p_ned, dtype=float)
        if not (np.all(np.isfinite(p)) and math.isfinite(fix.sigma_h)) or fix.sigma_h <= 0.0:
            counts.reject("non_finite")
            return None
        state = self.state
        if state is None:
            counts.reject("before_initialisation")
            self._pending_fix = fix
            return None
        if fix.t_ns < state.t_ns:
            counts.reject("older_than_filter")
            return None
        self._propagate_to(fix.t_ns, self._gyro, self._accel)
        if not self.position_initialized:
            self._init_position(fix)
            counts.used += 1
            return UpdateOutcome(True, 0.0, 3, "position initialised")
        if self.heading_aligned:
            outcome = self.gps.update(state, fix)
        else:
            outcome = self.gps.update(state, fix, held=self._held_until_aligned())
            solution = self._aligner.add_fix(p[:2], gps_sigmas(fix, self.options.gps_sigma_floor_m)[0])
            if solution is not None:
                self._apply_heading(solution)
        if outcome.accepted:
            counts.used += 1
        else:
            counts.reject(outcome.reason.replace(" ", "_"))
        return outcome

    def _held_until_aligned(self) -> np.ndarray:
        held = np.zeros(self.state.dim, dtype=bool)
        held[6:] = True  # attitude, biases and map wait for a heading
        return held

    def _init_position(self, fix: GpsFix) -> None:
        state = self.state
        sigma_h, sigma_v = gps_sigmas(fix, self.options.gps_sigma_floor_m)
        state.p = np.asarray(fix.p_ned, dtype=float) - state.R @ self.calibration.gps.lever_arm_b
        state.cov[0:3, :] = 0.0
        state.cov[:, 0:3] = 0.0
        state.cov[0:3, 0:3] = np.diag([sigma_h**2, sigma_h**2, sigma_v**2])
        self.position_initialized = True
        self.events.append((fix.t_ns, "position initialised from GPS"))

    def _apply_heading(self, solution: HeadingSolution) -> None:
        state = self.state
        psi = solution.yaw_correction
        rz = np.array([[math.cos(psi), -math.sin(psi), 0.0], [math.sin(psi), math.cos(psi), 0.0], [0.0, 0.0, 1.0]])
        state.q = quat_mul(quat_exp(np.array([0.0, 0.0, psi])), state.q)
        state.v = np.array([solution.velocity_h[0], solution.velocity_h[1], state.v[2]])
        cov = state.cov
        # Rotate the attitude block into the aligned frame, then replace the heading's
        # uncertainty by the fit's and forget its correlations (they were meaningless).
        cov[6:9, :] = rz @ cov[6:9, :]
        cov[:, 6:9] = cov[:, 6:9] @ rz.T
        cov[8, :] = 0.0
        cov[:, 8] = 0.0
        cov[8, 8] = solution.sigma**2
        cov[3:5, :] = 0.0
        cov[:, 3:5] = 0.0
        cov[3:5, 3:5] = np.eye(2) * max(solution.sigma_velocity, 0.02) ** 2
        self.heading_aligned = True
        self.heading_solution = solution
        self.events.append(
            (
                state.t_ns,
                f"heading aligned from GPS: correction {math.degrees(psi):.1f} deg, "
                f"sigma {math.degrees(solution.sigma):.2f} deg over {solution.window_s:.1f} s",
            )
        )

    # ------------------------------------------------------------------------------ output
    def pose(self) -> PoseEstimate | None:
        state = self.state
        if state is None:
            return None
        return PoseEstimate(
            t_ns=state.t_ns,
            p=state.p.copy(),
            v=state.v.copy(),
            q=state.q.copy(),
            omega_b=self._gyro - state.b_g,
            pose_cov=state.pose_covariance(),
            vel_cov=state.cov[3:6, 3:6].copy(),
            heading_aligned=self.heading_aligned,
            reset_counter=self.reset_counter,
        )

    def counts_report(self) -> dict:
        return {name: c.as_dict() for name, c in self.counts.items()}
