"""The estimator: start-up, IMU propagation and measurement updates, in time order.

Feed it samples in timestamp order (late measurements are ordered by ``vtolpose.estimator.fusion``);
ask it for the pose. Bad samples are counted per sensor and reason, never raised: the
caller always gets the best estimate the good data allow.

Start-up never waits for the motion: a still IMU gives roll, pitch and gyro bias (thesis 5.2),
and a vehicle that is not still within ``init.max_wait_s`` starts from the mean specific
force with wider sigmas. The heading comes from the dataset or operator, or is unknown: the
filter then works in a frame of arbitrary yaw, levelled by gravity, publishes that its heading
is unknown (a variance for a heading anywhere on the circle), and a bank of heading
hypotheses (``inertial/heading_bank.py``) places it from GPS once the motion shows it.

A vehicle that is moving from the start with a camera and no GPS is *initialising*: there is no
state (and nothing is published) until the visual-inertial start (``vtolpose.estimator.init``) has
solved a window of tracked features and IMU deltas and the EKF-SLAM starts from it; the status
says what the window still lacks. A GPS heard first gives the moving start a GPS gives, from its
first second of fixes and the IMU's latest window. Without GPS ever, position and (unless known)
heading are then the filter's own frame's: its origin and heading where it started
(``local_position``). A GPS that appears later joins that frame: its first second of fixes gives
the velocity, the last one the position, the heading bank the heading. Every running state was
handed over complete by the start-up coordinator (``estimator/start.py``): the running filter has
no half-started mode. A camera lost in its own frame drops the filter; the visual start begins again.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Callable

import numpy as np

from vtolpose.estimator.core import covariance
from vtolpose.estimator.core.calibration import Calibration, ImuNoise
from vtolpose.estimator.core.covariance import BG, TH, V
from vtolpose.estimator.vision.camera_pipeline import CameraOptions, CameraPipeline, FrameReport
from vtolpose.estimator.vision.camera_update import carry_gauge, heading_gauge
from vtolpose.estimator.vision.features import FrameFeatures
from vtolpose.estimator.vision.landmarks import INVERSE_DEPTH, landmark_points
from vtolpose.estimator.gnss.gps_update import GpsUpdater, place_at_fix
from vtolpose.estimator.gnss.noise_check import GpsNoiseCheck, NoiseCheckOptions
from vtolpose.estimator.inertial.gravity_update import GravityLeveller
from vtolpose.estimator.health import FrameInnovations, GapWidener, HealthMonitor, HealthOptions
from vtolpose.estimator.inertial.imu_delta import DeltaRun, ImuDelta, ImuDownsampler, delta_row
from vtolpose.estimator.inertial.initializer import InitialAttitude, InitOptions
from vtolpose.estimator.core.kalman import UpdateOutcome, chi2_gate, ekf_update
from vtolpose.estimator.core.measurements import GpsFix, RejectionCounts, readings_finite
from vtolpose.estimator.inertial.heading_bank import (
    UNKNOWN_HEADING_VAR, YAW, HeadingBank, HeadingBankOptions, with_bias_states,
)
from vtolpose.estimator.core.rotation import quat_from_euler, yaw_of
from vtolpose.estimator.inertial.propagator import ImuPropagator
from vtolpose.estimator.core.state import FilterState, StateLayout
from vtolpose.estimator.start import VELOCITY_FIT_S, StartCoordinator
from vtolpose.estimator.modes import FilterMode, HeadingMode, ModeEvent, ModeMachine
from vtolpose.estimator.status import EstimatorEvent, EstimatorStatus, EventKind, HeadingPlacement
from vtolpose.estimator.init.visual_inertial import VisualInertialInitializer, VisualInertialOptions, VisualInertialStart
from vtolpose.estimator.smoothing.recorder import FilterRecorder
from vtolpose.estimator.inertial.sample_kernel import level_run, plain_run
from vtolpose.estimator.inertial.stillness import StillChunk, StillnessDetector, StillnessOptions

HEADING_SOURCES = ("auto", "dataset", "gps")
# The steps of a compiled stretch that only propagated: their samples (indices into the run), end times, p, v, q
# (rows of 10) and robot covariances.
AfterSteps = Callable[[list[int], np.ndarray, np.ndarray, np.ndarray], None]
TILT_WEAK_SIGMA_RAD = math.radians(1.0)  # a map is started only under a tilt known this well (docs/estimator.md)
HEADING_WEAK_SIGMA_RAD = math.radians(5.0)  # a placed heading the camera waits for the GPS to narrow below this
LOST_POSITION_SIGMA_M = 100.0  # a rebuilt covariance without a usable position variance or a live GPS


@dataclass(slots=True)
class FilterOptions:
    variant: str = "biases"
    heading_source: str = "auto"  # auto: the dataset's known heading if any, else align from GPS
    heading_deg: float | None = None  # an operator-entered heading overrides both
    gps_gate: float | None = 16.27  # χ², 3 dof, 99.9 %: an outlier test, not a tenth of the good fixes; None: no gate
    gps_sigma_floor_m: float = 0.005
    gps_reset_after_s: float = 3.0  # every fix rejected for this long: the filter is lost, reset
    max_imu_gap_s: float = 0.1
    max_filter_rate_hz: float = 100.0  # IMU samples are accumulated into steps no faster than this
    unaligned_accel_noise: float = 0.2  # m/s²/√Hz floor of the extra horizontal noise while the heading is unknown
    level_interval_s: float = 0.1  # gravity levelling while the heading is unknown
    level_sigma: float = 2.0  # m/s²: the vehicle's own accelerations, averaged out over many updates
    noise: ImuNoise | None = None  # overrides the calibration's noise when given
    init: InitOptions = field(default_factory=InitOptions)
    align: HeadingBankOptions = field(default_factory=HeadingBankOptions)
    still: StillnessOptions = field(default_factory=StillnessOptions)
    camera: CameraOptions = field(default_factory=CameraOptions)
    visual_inertial: VisualInertialOptions = field(default_factory=VisualInertialOptions)
    health: HealthOptions = field(default_factory=HealthOptions)
    gps_noise: NoiseCheckOptions = field(default_factory=NoiseCheckOptions)

    def __post_init__(self) -> None:
        StateLayout(self.variant)  # validates the variant name
        if self.heading_source not in HEADING_SOURCES:
            raise ValueError(f"heading_source must be one of {', '.join(HEADING_SOURCES)}, got {self.heading_source!r}")


def published_cov9(cov: np.ndarray, heading_aligned: bool, local_heading_floor: float | None) -> np.ndarray:
    """:meth:`Estimator.published_cov9` of ``cov``, or of each of a stack of them (the last two axes: the steps
    of a run), under the modes given (``local_heading_floor``: :meth:`Estimator.local_heading_floor`)."""
    cov9 = covariance.nav_block(cov)
    if heading_aligned:
        return cov9
    if local_heading_floor is not None:
        cov9[..., YAW, YAW] = np.maximum(cov9[..., YAW, YAW], local_heading_floor)
        return cov9
    covariance.forget_yaw(cov9)
    cov9[..., YAW, YAW] = UNKNOWN_HEADING_VAR
    return cov9


class Estimator:
    def __init__(self, calibration: Calibration, options: FilterOptions | None = None,
                 recorder: FilterRecorder | None = None) -> None:
        """``recorder`` (the smoother's) sees every propagation and update from the first: given here, since a
        recorder that missed the start would smooth a trajectory it never saw begin."""
        opts = options or FilterOptions()
        if calibration.initial_gyro_bias_sigma is not None:  # the vehicle's IMU says how large its turn-on bias is
            opts = dataclasses.replace(opts, init=dataclasses.replace(opts.init, sigma_gyro_bias=calibration.initial_gyro_bias_sigma))
        self.options = opts
        self.calibration = calibration
        self.layout = StateLayout(opts.variant)
        self.noise = opts.noise or calibration.imu.noise
        self.gps = GpsUpdater(calibration.gps.lever_arm_b, opts.gps_gate, opts.gps_sigma_floor_m)
        self.counts = {name: RejectionCounts() for name in ("imu", "gps", "still", "level")}
        self.state: FilterState | None = None
        self.propagator: ImuPropagator | None = None
        self.heading_placement: HeadingPlacement | None = None  # how the bank placed the heading
        self.reset_counter = 0
        self.events: list[EstimatorEvent] = []  # start-up, alignment, resets
        self.gps_noise = GpsNoiseCheck(opts.gps_noise, opts.gps_sigma_floor_m,  # claimed sigmas checked
                                       lambda t_ns, text: self._event(t_ns, EventKind.GPS_NOISE, text))
        heading, self._heading_sigma = self._known_heading()
        self._heading_known = heading is not None  # configuration: the dataset's or the operator's heading
        # The modes (estimator.modes): changed only by self.modes.fire(event), where the conditions below hold.
        self.modes = ModeMachine(self._heading_known)
        self._bank: HeadingBank | None = None  # heading hypotheses while the heading is unknown
        self._bank_gps = GpsUpdater(calibration.gps.lever_arm_b, None, opts.gps_sigma_floor_m)  # no gate: every fix weighs
        self._stillness = StillnessDetector(opts.still)
        self._leveller: GravityLeveller | None = None
        self._level_sum, self._level_n, self._level_t0 = np.zeros(3), 0, 0
        self._fixed_bias_var = np.zeros(3)  # thesis variant: variance of its calibrated gyro bias
        self._last_fix: GpsFix | None = None  # the latest usable fix (a reset re-initialises from it)
        self._gps_reset_t: int | None = None  # the last reset for rejected fixes (a second one soon after re-aligns)
        self.health = HealthMonitor(opts.health, opts.gps_reset_after_s)
        self._gap = GapWidener(opts.health, opts.max_imu_gap_s)
        self._downsampler = ImuDownsampler(opts.max_filter_rate_hz)
        self._fuses_runs = False  # it has taken runs of samples: their kernels are loaded (process_imu_run)
        self._horizontal_accel = np.zeros(2)  # horizontal acceleration, averaged (see _propagate)
        self._accel_at_rest = np.zeros(2)  # what it read at the last still chunk
        self._last_imu_t: int | None = None
        self._ahead: tuple[int, np.ndarray, np.ndarray] | None = None  # the next IMU sample, while known (imu_ahead)
        self._lost_before_next_s = 0.0  # refused IMU data the next sample must account for (imu_discontinuity)
        self._gyro = np.zeros(3)
        # The camera as the features see it: a frame wider than the working width is reduced first (working_frame).
        cam = calibration.camera.working(opts.camera.working_width) if calibration.camera is not None else None
        self.camera = CameraPipeline(cam, opts.camera) if cam is not None else None
        self._last_frame: tuple[int, bytes] | None = None  # time and digest of the last frame received
        # Facts of the input's history, not modes: how the filter started (a start in motion: the camera waits
        # for the heading bank) and whether any usable GPS fix was heard (no visual start then, no own frame).
        self._moving_start = False
        self._gps_seen = False
        self._gps_heard_ns: int | None = None  # the last usable fix's time, before the start too
        self.visual_inertial = None
        if cam is not None and opts.visual_inertial.enabled:
            self.visual_inertial = VisualInertialInitializer(cam, self.noise, calibration.imu.gravity, opts.camera.pixel_sigma,
                                                             opts.visual_inertial, opts.camera.association)
        self._starter = StartCoordinator(self.layout, opts.init, calibration.imu.gravity, heading, self._heading_sigma,
                                         opts.gps_sigma_floor_m, self.visual_inertial)
        # Sees every propagation (and, through the state, every update) for the smoother; None: off.
        self.recorder = recorder

    @property
    def initialized(self) -> bool:
        return self.state is not None

    @property
    def mode(self) -> FilterMode:
        return self.modes.mode

    @property
    def heading_mode(self) -> HeadingMode:
        return self.modes.heading

    @property
    def heading_aligned(self) -> bool:
        return self.modes.heading_aligned

    @property
    def position_initialized(self) -> bool:
        return self.modes.mode.position_from_gps

    @property
    def local_position(self) -> bool:
        """No GPS heard at all, but the camera holds the filter's own frame: its origin where it started and,
        unless one was known, its heading the one it started with (the yaw gauge of an unknown heading)."""
        return self.modes.mode.local_position

    def _known_heading(self) -> tuple[float | None, float]:
        """Initial heading and its sigma [rad]; (None, 0) when it must come from GPS."""
        opts = self.options
        default_sigma = math.radians(opts.init.sigma_heading_known_deg)
        if opts.heading_deg is not None:
            return math.radians(opts.heading_deg), default_sigma
        if opts.heading_source == "gps":
            return None, 0.0
        cal = self.calibration
        if opts.heading_source == "dataset" and cal.initial_heading_rad is None:
            raise ValueError("heading_source 'dataset' but the dataset gives no initial heading")
        if cal.initial_heading_rad is None:
            return None, 0.0
        return cal.initial_heading_rad, cal.initial_heading_sigma_rad or default_sigma

    # -------------------------------------------------------------------------------- IMU
    def process_imu(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray) -> bool:
        """Propagate to ``t_ns``. Returns False when the sample was rejected (and counted)."""
        counts = self.counts["imu"]
        counts.received += 1
        # One dot product is finite exactly when every component is (cheaper than isfinite).
        if not readings_finite(gyro, accel):
            counts.reject("non_finite")
            return False
        if self._last_imu_t is not None and t_ns <= self._last_imu_t:
            counts.reject("time_not_increasing")
            return False
        counts.used += 1
        if self.state is not None:
            self._end_gap(t_ns)
        self._last_imu_t = t_ns
        self._gyro = gyro
        delta = self._downsampler.add(t_ns, gyro, accel)
        if self.state is None:
            if delta is not None and self._visual_start_pending():
                self.visual_inertial.add_delta(delta)
            if self.mode is FilterMode.INITIALISING:  # the visual window gives the start (or a GPS heard meanwhile)
                self._starter.initializer.keep(t_ns, gyro, accel)
                return True
            # Not still within max_wait_s (rotors turning, carried, flying): start from the
            # accelerometer alone rather than wait for a rest or a manoeuvre that may never come.
            init = self._starter.initializer.add(t_ns, gyro, accel)
            if init is not None:
                self._downsampler.flush()  # the filter starts at this sample
                self._start(init)
            return True
        if delta is not None:
            self._propagate(delta)
            if self.health.check_due(t_ns):
                self._check_state()
        if not self.heading_aligned:
            self._level(t_ns, accel)
        if self.options.still.enabled:
            state = self.state
            vx, vy, vz = state.v.tolist()
            chunk = self._stillness.add(t_ns, gyro, accel, self.propagator.gravity[2], math.sqrt(vx * vx + vy * vy + vz * vz))
            if chunk is not None:
                self._apply_still(chunk)
        return True

    @property
    def takes_runs(self) -> bool:
        """Whether :meth:`process_imu_run` would take a plain run now (a running filter, no lost time to widen for)."""
        return self.state is not None and not self._lost_before_next_s and self._last_imu_t is not None

    def process_imu_run(self, t_arr: np.ndarray, gyro: np.ndarray, accel: np.ndarray,
                        after_step: Callable[[int], None], after_steps: AfterSteps | None = None) -> bool:
        """:meth:`process_imu` for each row of a run of samples, ``after_step(k)`` after each sample ``k`` that
        ended a filter step, and after the first. What does not depend on the state (the steps' deltas, the rest detector's sums)
        is worked out for the whole run at once; the state sees the same operations in the same order.
        ``after_steps``: takes, in one call, the steps of a compiled stretch that only propagated, in place of
        their ``after_step`` calls (see :meth:`_compiled_steps`).

        Only for a running filter (:attr:`takes_runs`) and a plain run (every sample finite, later than
        the one before, no gap to widen for): False, with nothing done, otherwise (the caller then goes
        sample by sample). While the heading is unknown the levelling's sums are worked out for the run
        too, and each interval's update made at its last sample.
        """
        n = len(t_arr)
        if not self.takes_runs or n == 0 or not plain_run(t_arr, gyro, accel, self._last_imu_t, self.options.max_imu_gap_s):
            return False
        self._fuses_runs = True
        t_ns = t_arr.tolist()
        counts = self.counts["imu"]
        counts.received += n
        counts.used += n
        self._gap.end()
        steps = self._downsampler.add_run(t_arr, gyro, accel)
        step_at = {k: j for j, k in enumerate(steps.ends)}  # at most one step ends at a sample
        chunks = {k: (duration, stats) for k, duration, stats in self._stillness.add_run(t_arr, gyro, accel)} \
            if self.options.still.enabled else {}
        levels = self._level_run(t_arr, accel) if not self.heading_aligned else {}
        # Each sample's work in process_imu's order; the first sample is always offered to after_step, for
        # the state may have moved before it (a measurement's partial step), as sample by sample.
        order = sorted(step_at.keys() | chunks.keys() | levels.keys() | {0})
        i = 0
        head = False  # the first sample's pose waits to go first among the compiled steps that follow it
        while i < len(order):
            k = order[i]
            j = step_at.get(k)
            if j is not None:
                taken = self._compiled_steps(order, i, step_at, chunks, levels, steps, t_ns, gyro, after_step, after_steps,
                                             head)
                head = False
                if taken:
                    i += taken
                    continue
            i += 1
            self._last_imu_t, self._gyro = t_ns[k], gyro[k]
            if j is not None:
                self._propagate(steps.delta(j))
                if self.health.check_due(t_ns[k]):
                    self._check_state()
            self._level_and_rest(levels.get(k), chunks.get(k))
            if j is not None or k == 0:
                if j is None and after_steps is not None and i < len(order) and order[i] in step_at:
                    head = True  # a step follows: the pose goes with its stretch (or on its own if that declines)
                else:
                    after_step(k)
        self._last_imu_t = t_ns[-1]
        self._gyro = gyro[n - 1]
        return True

    def _level_and_rest(self, f_mean: np.ndarray | None, chunk: tuple | None) -> None:
        """A sample's measures after its step, as :meth:`process_imu` makes them: the levelling, then the rest chunk."""
        if f_mean is not None:
            self._apply_level(f_mean)
        if chunk is not None:
            vx, vy, vz = self.state.v.tolist()
            still = self._stillness.judge(*chunk, self.propagator.gravity[2], math.sqrt(vx * vx + vy * vy + vz * vz))
            if still is not None:
                self._apply_still(still)

    def _compiled_steps(self, order: list[int], i: int, step_at: dict[int, int], chunks: dict, levels: dict,
                        steps: DeltaRun, t_ns: list[int], gyro: np.ndarray, after_step: Callable[[int], None],
                        after_steps: AfterSteps | None = None, head: bool = False) -> int:
        """The steps from ``order[i]`` on that need nothing but propagation (no rest chunk, levelling or periodic
        check before the last), in one compiled call (``propagator.propagate_steps``), then each step's
        bookkeeping, the last sample's levelling or rest chunk if it has one, and ``after_step`` in turn,
        the state as :meth:`_propagate` leaves it. With ``after_steps``, the state takes the last step's p, v, q
        and covariance at once, and the steps that only propagated (all, or all but a last one with measures or
        the check) are handed to it in one call in place of their ``after_step`` (their samples, end times,
        p, v, q rows and covariances: nothing else changed the state meanwhile), before the last one's measures.
        ``head``: the run's first sample (no step of its own) is owed its ``after_step``, due before these steps;
        its pose, the state as it is now, goes first in their ``after_steps`` call (or ``after_step(0)`` before
        anything changes, where no steps go to ``after_steps``).
        While the heading is unknown the steps have its extra noise, and the heading hypotheses take the same
        steps in one compiled call of their own. Returns how many were taken: none while a
        recorder watches the steps, or where the propagator has no compiled sequence (a map, non-isotropic
        noise), the head's ``after_step`` made first."""
        if self.recorder is not None:
            if head:
                after_step(0)
            return 0
        end = i
        measured = False  # the last step has measures or the check
        while end < len(order):
            k = order[end]
            if k not in step_at:
                break
            end += 1
            if k in chunks or k in levels or self.health.check_would_be_due(t_ns[k]):
                measured = True
                break  # the measures or the check change the state: the next steps start from what they leave
        j0, j1 = step_at[order[i]], step_at[order[end - 1]] + 1
        state = self.state
        computed = self._stretch(steps.deltas[j0:j1], steps.dts[j0:j1], int(steps.times[j1 - 1, 1]),
                                 head and after_steps is not None)
        if computed is None:
            if head:
                after_step(0)
            return 0
        states, covs, means = computed
        m = end - i
        ends = steps.times[j0:j1, 1]
        if after_steps is not None:
            clean = m - 1 if measured else m
            if head and clean:  # the first sample's pose: the state before these steps, their first row
                ks = [0, *order[i:i + clean]]
                ends_clean = np.empty(clean + 1, np.int64)
                ends_clean[0], ends_clean[1:] = state.t_ns, ends[:clean]
            else:
                if head:
                    after_step(0)
                ks, ends_clean = order[i:i + clean], ends[:clean]
            o = 1 if head else 0  # the first row is the state before the steps
            states_clean, covs_clean = states[:clean + o], covs[:clean + o]
            # The state as the stretch's steps leave it, then their poses at once: all but a last step with measures.
            k, row = order[end - 1], states[m - 1 + o]
            self._last_imu_t, self._gyro, self._horizontal_accel = t_ns[k], gyro[k], means[m - 1 + o]
            # A copy: the state's covariance is changed in place by the next update, the steps' are kept as they are.
            state.p, state.v, state.q, state.cov, state.t_ns = (row[0:3], row[3:6], row[6:10], covs[m - 1 + o].copy(),
                                                                int(ends[m - 1]))
            if clean:
                after_steps(ks, ends_clean, states_clean, covs_clean)
            if measured:
                if self.health.check_due(t_ns[k]):
                    self._check_state()
                self._level_and_rest(levels.get(k), chunks.get(k))
                after_step(k)
            return m
        ends = ends.tolist()
        for x in range(m):
            k = order[i + x]
            self._last_imu_t, self._gyro = t_ns[k], gyro[k]
            row = states[x]
            state.p, state.v, state.q, state.cov, state.t_ns = row[0:3], row[3:6], row[6:10], covs[x], ends[x]
            self._horizontal_accel = means[x]
            if self.health.check_due(t_ns[k]):
                self._check_state()
            self._level_and_rest(levels.get(k), chunks.get(k))  # only the last step's sample may have any
            after_step(k)
        return m

    def _propagate(self, delta: ImuDelta) -> None:
        extra = 0.0
        if not self.heading_aligned and self._bank is not None:
            self._bank.propagate(delta)
        if not (self.heading_aligned or self.local_position):  # a frame of its own needs no world heading
            # An unknown heading misplaces the horizontal acceleration by up to twice its size;
            # at rest that is nothing, so the filter can still tell it is at rest. The vehicle's
            # acceleration, that is: vibration (zero mean, tens of hertz) is in the IMU noise
            # already, so it is averaged over init.average_s first, and what the tilt and bias
            # errors make of gravity (the reading at the last still chunk) is taken off.
            ax, ay = (self._horizontal_accel - self._accel_at_rest).tolist()
            extra = max(self.options.unaligned_accel_noise, 2.0 * math.sqrt(ax * ax + ay * ay))  # as step_run does
        recorder = self.recorder
        if recorder is not None:
            recorder.before_propagation(self.state, self.heading_aligned)
        a_w = self.propagator.propagate(self.state, delta, extra)
        average_s = self.options.init.average_s
        keep = average_s / (average_s + delta.dt)
        hx, hy = self._horizontal_accel.tolist()
        ax, ay, _ = a_w.tolist()
        self._horizontal_accel = np.array([keep * hx + (1.0 - keep) * ax, keep * hy + (1.0 - keep) * ay])
        self.state.t_ns = delta.t1_ns
        if recorder is not None:
            recorder.after_propagation(self.state, self.propagator.transition)

    def _forget_heading(self) -> None:
        """The heading becomes unknown: the filter's frame gets an arbitrary yaw, a gauge rather than an
        error (landmarks, if any, share it), so its variance starts from zero. What the heading may be —
        anywhere on the circle — is what :meth:`published_cov9` says."""
        covariance.forget_yaw(self.state.cov)

    def published_cov9(self) -> np.ndarray:
        """Covariance of [δp, δv, δθ] as the outputs publish it: the filter's, except that an unknown
        heading has the variance of a heading uniform on the circle, uncorrelated with the rest. In a
        frame of its own (``local_position``) the heading is the frame's: its variance is the filter's,
        what the heading may have drifted since the start (never below the start's own gauge sigma)."""
        return published_cov9(self.state.cov, self.heading_aligned, self.local_heading_floor())

    def local_heading_floor(self) -> float | None:
        """In a frame of its own, the variance its published heading never falls below (the start's gauge sigma,
        squared); None in the world's frame."""
        return math.radians(self.options.visual_inertial.heading_sigma_deg) ** 2 if self.local_position else None

    def imu_discontinuity(self, lost_s: float) -> None:
        """``lost_s`` of IMU data before the next sample were refused (stamped in the past: a backward
        clock step): the vehicle moved meanwhile, the filter's clock did not. Widened like a long gap."""
        self._lost_before_next_s += max(float(lost_s), 0.0)

    def _in_gap(self, t_ns: int) -> None:
        """Time reaches ``t_ns`` with no IMU sample since ``_last_imu_t``: widen for it (estimator.health);
        past ``imu_gap_reset_s`` stop extrapolating the last sample — a reset, the state held."""
        state = self.state
        if state is None or self._last_imu_t is None:
            return
        gap_s = (t_ns - self._last_imu_t) * 1e-9
        if self._gap.widen(state, gap_s, self._gyro - state.b_g):
            self.counts["imu"].flag("gap_reset")
            tail = self._downsampler.flush()
            if tail is not None:
                self._propagate(tail)
            self._downsampler = ImuDownsampler(self.options.max_filter_rate_hz)  # no more holding the last sample
            self._reset(t_ns, "imu_gap", f"no IMU sample for {self.options.health.imu_gap_reset_s:g} s (samples lost "
                        "or a clock step): the state is held, not extrapolated; covariance widened", clear_map=False)
            self.health.imu_missing(self._last_imu_t)  # until the next sample: the held pose is not published as good
        if self._gap.holding:
            state.t_ns = max(state.t_ns, t_ns)

    def _end_gap(self, t_ns: int) -> None:
        """An IMU sample at ``t_ns``: account for the gap before it (if any), then it is over."""
        state = self.state
        if self._lost_before_next_s:
            lost, self._lost_before_next_s = self._lost_before_next_s, 0.0
            if self._gap.lost(state, lost, self._gyro - state.b_g):
                self.counts["imu"].flag("gap_reset")
                self._reset(t_ns, "imu_gap", f"{lost:.3f} s of IMU samples stamped in the past (a clock step back): "
                            "the state is held over them, covariance widened", clear_map=False)
            return
        gap_s = (t_ns - self._last_imu_t) * 1e-9 if self._last_imu_t is not None else 0.0
        if gap_s > self.options.max_imu_gap_s:
            self._in_gap(t_ns)
            self.health.imu_missing(None)  # the IMU is back
            if not self._gap.holding:
                self.counts["imu"].flag("gap_bridged")  # extrapolated over, widened
            else:
                self._downsampler = ImuDownsampler(self.options.max_filter_rate_hz)  # the next step starts here
        self._gap.end()

    def _check_state(self) -> None:
        """Periodic: a state that is not finite or not positive definite is rebuilt from what is still sound."""
        problem = self.health.check(self.state)
        if problem is None:
            return
        state, snap = self.state, self.health.snapshot
        nominal = (state.p, state.v, state.q, state.b_g, state.b_a)
        if snap is not None and not all(np.all(np.isfinite(x)) for x in nominal):
            state.p, state.v, state.q, state.b_g, state.b_a = (x.copy() for x in (snap.p, snap.v, snap.q, snap.b_g, snap.b_a))
        var_p = covariance.block_variances(state.cov, covariance.P)
        if not (np.all(np.isfinite(var_p)) and np.all(var_p > 0.0)):
            var_p = np.full(3, LOST_POSITION_SIGMA_M**2)
        state.robot_only(self._reset_covariance(var_p))  # the map goes (_reset clears the book)
        if self.position_initialized and self._last_fix is not None and self.health.fresh("gps", state.t_ns):
            self._init_position(self._last_fix)  # the GPS is alive: position from it
        self._reset(state.t_ns, "state_invalid",
                    f"{problem}: nominal state from the last sound check, covariance re-initialised, map cleared")

    def _reset_covariance(self, var_p: np.ndarray) -> np.ndarray:
        """The robot covariance a reset rebuilds: position variances ``var_p``, the rest a start in motion's."""
        init = self.options.init
        return covariance.robot_reset(self.layout, var_p, init.sigma_velocity_moving,
                                      math.radians(init.sigma_attitude_moving_deg), init.sigma_gyro_bias, init.sigma_accel_bias)

    def _reset(self, t_ns: int, kind: str, reason: str, clear_map: bool = True) -> None:
        """Count a reset (ODOMETRY reset_counter), note it; landmarks placed by the old estimate go."""
        if clear_map and self.camera is not None and self.state is not None:
            self.camera.clear(self.state)
        self.reset_counter += 1
        self._bank = None  # its hypotheses followed the old estimate: they start again at the next fix
        self.health.record_reset(t_ns, kind, reason)
        self._event(t_ns, EventKind.RESET, f"reset #{self.reset_counter}: {reason}", reset_kind=kind)

    def imu_ahead(self, sample: tuple[int, np.ndarray, np.ndarray] | None) -> None:
        """The IMU sample that follows the measurements about to be applied (time, gyro, accel), or None: the
        fusion horizon keeps it buffered. A measurement between two samples is then reached with the reading
        interpolated to its time, not the last one held (:meth:`ImuDownsampler.hold`)."""
        self._ahead = sample

    def _next_sample(self, t_ns: int) -> tuple[int, np.ndarray, np.ndarray] | None:
        """The next sample to interpolate towards at ``t_ns``: the one :meth:`imu_ahead` gave, if it is after
        ``t_ns`` and within the gap the filter steps over (beyond it the last reading is held, as in a gap)."""
        ahead, last = self._ahead, self._last_imu_t
        if ahead is None or last is None or ahead[0] <= t_ns or (ahead[0] - last) * 1e-9 > self.options.max_imu_gap_s:
            return None
        return ahead

    def _propagate_to(self, t_ns: int) -> None:
        """Bring the state to a measurement's time: the partial step, then the step to it from the last
        sample, with the reading interpolated towards the next sample if known (else held)."""
        if self._last_imu_t is not None and (t_ns - self._last_imu_t) * 1e-9 > self.options.max_imu_gap_s:
            self._in_gap(t_ns)
        if self._fuses_runs:  # the same deltas and steps, each in one compiled call (kernels a live service never loads)
            times, dts, deltas = self._downsampler.to_time(t_ns, self._next_sample(t_ns))
            if len(dts) and not self._propagate_steps(times, dts, deltas):
                for j in range(len(dts)):
                    self._propagate(delta_row(times, dts, deltas, j))
            return
        for delta in (self._downsampler.flush(), self._downsampler.hold(t_ns, self._next_sample(t_ns))):
            if delta is not None:
                self._propagate(delta)

    def _propagate_steps(self, times: np.ndarray, dts: np.ndarray, deltas: np.ndarray) -> bool:
        """:meth:`_propagate` of each delta (rows of (t0, t1), dt, [Δθ, Δv]) in one compiled call, the heading
        hypotheses' in one of their own; False, with nothing done, where only :meth:`_propagate` applies
        (a recorder watching the steps, a map, noise that is not isotropic)."""
        if self.recorder is not None:
            return False
        computed = self._stretch(deltas, dts, int(times[-1, 1]))
        if computed is None:
            return False
        states, covs, means = computed
        row, state = states[-1], self.state
        state.p, state.v, state.q, state.cov, state.t_ns = row[0:3], row[3:6], row[6:10], covs[-1], int(times[-1, 1])
        self._horizontal_accel = means[-1]
        return True

    def _stretch(self, deltas: np.ndarray, dts: np.ndarray, t_end: int,
                 start_row: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The state's steps over ``deltas`` as :meth:`_propagate` takes them (the extra noise while the heading is
        unknown) in one compiled call, the state itself left as it was (``propagator.propagate_steps``: rows of
        p, v, q, covariances, means; ``start_row``: the state before them first), and the heading hypotheses
        taken over the same steps to ``t_end``. None, with nothing done, where either declines."""
        unaligned = not (self.heading_aligned or self.local_position)  # as _propagate
        computed = self.propagator.propagate_steps(self.state, deltas, dts, self._horizontal_accel,
                                                   self.options.init.average_s,
                                                   self.options.unaligned_accel_noise if unaligned else None,
                                                   self._accel_at_rest, start_row)
        bank = self._bank if not self.heading_aligned else None
        if computed is None or (bank is not None and not bank.propagate_run(deltas, dts, t_end)):
            return None
        return computed

    # ---------------------------------------------------------------------------- start-up
    def _begin(self, state: FilterState, gravity: float, message: str) -> None:
        self.state = state
        self.propagator = ImuPropagator(self.noise, gravity)
        self._leveller = GravityLeveller(gravity, self.options.level_sigma, chi2_gate(3, 0.999))
        self._level_t0 = state.t_ns
        self._event(state.t_ns, EventKind.STARTED, message)

    def _start(self, init: InitialAttitude) -> None:
        """Adopt the start the IMU's window gives (estimator.start)."""
        camera = self.counts.get("camera")
        start = self._starter.from_imu(init, camera is not None and camera.received > 0, self._gps_seen)
        self.modes.fire(start.event)
        self._moving_start = start.moving
        if not self.mode.initialised:  # moving, camera only: the visual-inertial window will give the start
            self._event(init.t_ns, EventKind.INITIALISING, start.message)
            return
        self._fixed_bias_var = start.fixed_bias_var
        self._begin(start.state, start.gravity, start.message)
        if not self.heading_aligned:
            self._bank = self._new_bank(start.state, None)
        if start.place_at is not None:  # a moving vehicle waits for the next fix
            self._init_position(start.place_at)

    def _visual_start_pending(self) -> bool:
        """Whether the visual-inertial start is wanted: a camera, no GPS heard, no running filter."""
        return self.visual_inertial is not None and not self._gps_seen and self.state is None

    def _start_from_gps_heard(self) -> None:
        """Initialising, and a second of fixes heard: the moving start the GPS gives, from the IMU's latest window."""
        if self.mode is not FilterMode.INITIALISING or not self._starter.heard_for(VELOCITY_FIT_S):
            return
        init = self._starter.initializer.latest()
        if init is not None:
            self._downsampler.flush()  # the filter starts at the window's last sample
            self._start(init)

    def _apply_visual_start(self, window: VisualInertialStart) -> None:
        """Start (or, after the camera was lost, start again) EKF-SLAM from a converged visual-inertial window,
        its landmarks included. An unknown heading stays unknown: the frame's yaw is a gauge (its variance
        zero, held by the camera)."""
        start = self._starter.from_window(window)
        state = start.state
        self._fixed_bias_var = start.fixed_bias_var
        self._begin(state, start.gravity, start.message)
        self.modes.fire(ModeEvent.VISUAL_START)
        if not self.heading_aligned:
            self._forget_heading()
        self.camera.adopt(state, start.descriptors, start.landmark_sigmas)
        self.visual_inertial.reset()

    def _join_gps(self, fix: GpsFix) -> bool:
        """A GPS heard for the first time by a filter in the camera's own frame: its fixes are collected for a second (estimator.start); then they give the velocity, the last
        one the position, the heading bank the heading — the moving start the GPS would have given. The
        map, placed in the old frame, goes. Returns True once joined."""
        joined = self._starter.join(fix)
        if joined is None:
            return False
        velocity, state = joined.velocity, self.state
        if velocity is not None:
            state.v = velocity[0]
            covariance.reinitialise(state.cov, V, velocity[1])
        else:
            covariance.reinitialise(state.cov, V, np.eye(3) * self.options.init.sigma_velocity_moving**2)
        if self.camera is not None:
            self.camera.clear(state)
        self.modes.fire(ModeEvent.GPS_JOINED)
        if self.visual_inertial is not None:
            self.visual_inertial.reset()
        self._init_position(fix)
        self.reset_counter += 1  # the frame jumps to the GPS's
        self._event(fix.t_ns, EventKind.GPS_JOINED, f"GPS joined: velocity from {joined.fixes_used} fixes, position from "
                    f"the last; reset #{self.reset_counter}", fixes=joined.fixes_used)
        if not self.heading_aligned:
            self._bank = self._new_bank(state, None)
            self._bank.update(fix)  # positions the hypotheses
        return True

    def _new_bank(self, state: FilterState, velocity_sigma: float | None) -> HeadingBank:
        """Hypotheses around ``state``; they always carry bias states (the thesis model takes its fixed
        biases from them, measured in flight, when the heading is placed)."""
        start = with_bias_states(state, np.sqrt(self._fixed_bias_var), self.options.init.sigma_accel_bias)
        return HeadingBank(self.options.align, start, self.propagator, self._bank_gps, velocity_sigma)

    def _place_heading(self, placed: FilterState, fix_t_ns: int) -> None:
        """The bank has found the heading: its best hypothesis becomes the robot state. Landmarks
        placed in the frame of arbitrary yaw go with it."""
        bank = self._bank
        if self.camera is not None:
            self.camera.clear(self.state)
        state = self.state
        state.p, state.v, state.q, state.b_g, state.b_a = placed.p, placed.v, placed.q, placed.b_g, placed.b_a
        state.robot_only(covariance.robot_block(placed.cov, self.layout.robot_dim))
        self._fixed_bias_var = covariance.block_variances(placed.cov, BG)  # the thesis model keeps b_g at this
        self.modes.fire(ModeEvent.HEADING_PLACED)
        self._bank = None
        heading, sigma = bank.heading()
        self.heading_placement = HeadingPlacement(fix_t_ns, math.degrees(heading), math.degrees(sigma), bank.fixes,
                                                  len(bank.members), float(bank.weights.max()))
        sd = np.degrees(np.sqrt(covariance.block_variances(state.cov, TH)))
        self._event(fix_t_ns, EventKind.HEADING_PLACED, f"heading placed from {bank.fixes} GPS fixes by {len(bank.members)} "
                    f"hypotheses: {math.degrees(heading):.1f} deg, attitude sigma {sd[0]:.2f}/{sd[1]:.2f}/{sd[2]:.2f} deg",
                    heading_deg=math.degrees(heading), sigma_deg=math.degrees(sigma), fixes=bank.fixes)

    # -------------------------------------------------------------------------------- GPS
    def process_gps(self, fix: GpsFix) -> UpdateOutcome | None:
        """Fuse a fix at its own time. Returns the update outcome, or None if it was not fused."""
        counts = self.counts["gps"]
        counts.received += 1
        north, east, down = np.asarray(fix.p_ned, dtype=float).tolist()
        if not (math.isfinite(north) and math.isfinite(east) and math.isfinite(down) and math.isfinite(fix.sigma_h)) \
                or fix.sigma_h <= 0.0:
            counts.reject("non_finite")
            self.health.measured("gps", fix.t_ns, used=False)  # alive, but not usable
            return None
        self._gps_heard_ns = fix.t_ns
        # The GPS noise check: the fix weighed with the noise it really has when its claim is not believed.
        raw, fix = fix, self.gps_noise.believed(fix)
        state = self.state
        if state is not None and fix.t_ns < state.t_ns:
            counts.reject("older_than_filter")
            return None
        if state is None:
            self._gps_seen = True
            self._starter.hear(fix)
            if self.gps_noise.before_start(raw):  # the GPS noise check: the fixes held weighed as it now believes
                self._starter.reweigh(self.gps_noise.believed)
            self._start_from_gps_heard()
            counts.reject("before_start")
            return None
        self._propagate_to(fix.t_ns)
        self._last_fix = fix
        if self.mode.joining or self.local_position:
            self._gps_seen = True
            if not self.mode.joining:
                self.modes.fire(ModeEvent.GPS_HEARD)
            if not self._join_gps(fix):
                counts.reject("joining")
                return None
            counts.used += 1
            self.health.measured("gps", fix.t_ns, used=True)
            return UpdateOutcome(True, 0.0, 3, "GPS joined")
        self._gps_seen = True
        if not self.position_initialized:
            self.modes.fire(ModeEvent.GPS_HEARD)
            self._init_position(fix)
            counts.used += 1
            self.health.measured("gps", fix.t_ns, used=True)
            return UpdateOutcome(True, 0.0, 3, "position initialised")
        aligned = self.heading_aligned
        posterior = None  # the fix's residual after its update, where the compiled fix works it out
        if aligned and not state.n_landmarks and not state.calib.shape[0] and state.cov.flags.c_contiguous:
            # IMU+GPS: the noise check's innovation (1/2), the update and the posterior residual in one call.
            outcome, info = self.gps.update_filter(state, fix, self.gps_noise.claims(raw))
            self.gps_noise.innovation(raw, info[3:6], float(info[2]))
            posterior = info[6:9]
        else:
            self.gps_noise.before_update(state, raw, self.gps.model)  # the GPS noise check (1/2)
            gauge = heading_gauge(state)
            if aligned:
                outcome = self.gps.update(state, fix)
            else:
                outcome = self.gps.update_heading_unknown(state, fix, self._held_until_aligned())
            carry_gauge(state, gauge)  # the map's heading gauge follows the move (camera_update.carry_gauge)
        if outcome.accepted:
            counts.used += 1
        else:
            counts.reject(outcome.reason.replace(" ", "_"))
        gated = outcome.accepted or outcome.reason == "chi2 gate"
        self.health.innovations("gps", fix.t_ns, outcome.accepted if gated else None,
                                "" if outcome.accepted else f"fix refused by the gate (NIS {outcome.nis:.1f})")
        if self.health.measured("gps", fix.t_ns, outcome.accepted, gated=True):
            self._reset_from_gps(raw)
            posterior = None  # against the state the reset made
        self._noise_checked(raw, fix, outcome.accepted, posterior)  # the GPS noise check (2/2)
        if not self.heading_aligned:
            self._search_heading(fix)
        return outcome

    def _noise_checked(self, raw: GpsFix, weighed: GpsFix, accepted: bool, posterior: np.ndarray | None = None) -> None:
        """The GPS noise check sees the fix's residual after its update (``posterior``, when worked out already);
        a change of belief is an event."""
        residual = self.gps.residual(self.state, raw) if posterior is None else posterior
        self.gps_noise.after_update(raw.t_ns, residual, accepted)
        if weighed is not raw:
            self.counts["gps"].flag("sigma_not_believed")

    def _search_heading(self, fix: GpsFix) -> None:
        """Feed the heading hypotheses. After a reset they start again from the filter's state, but
        its velocity was carried by an accelerometer turned by an unknown heading: they take it
        with a moving start's sigma and their position from the next fix."""
        if self._bank is None:
            self._bank = self._new_bank(self.state, self.options.init.sigma_velocity_moving)
            return
        self._bank.update(fix)
        placed = self._bank.placed()
        if placed is not None:
            self._place_heading(placed, fix.t_ns)

    def _held_until_aligned(self) -> np.ndarray:
        held = np.zeros(self.state.dim, dtype=bool)
        held[TH.start :] = True  # attitude, biases and map wait for a heading
        return held

    def _init_position(self, fix: GpsFix) -> None:
        place_at_fix(self.state, fix, self.calibration.gps.lever_arm_b, self.options.gps_sigma_floor_m)
        self._event(fix.t_ns, EventKind.POSITION_INITIALISED, "position initialised from GPS")

    def _reset_from_gps(self, fix: GpsFix) -> None:
        """Every fix rejected for ``gps_reset_after_s``: the estimate, not the GPS, is wrong.

        Position and velocity are taken from GPS, and a heading the filter found itself may be what
        is wrong with it: that is searched for again. If the fixes are still refused right after
        that, the attitude is wrong too (a damaged gyro reading turned it): it starts again level,
        as a moving start does, and gravity and the heading hypotheses find it again.
        """
        fix = self.gps_noise.on_reset(fix)  # from the second reset in a row: the noise the fixes really have
        state, after_s = self.state, self.options.gps_reset_after_s
        again = self._gps_reset_t is not None and (fix.t_ns - self._gps_reset_t) * 1e-9 <= 2.0 * after_s
        self._gps_reset_t = fix.t_ns
        what = "position and velocity re-initialised from GPS"
        if self.heading_mode is HeadingMode.PLACED:
            self.modes.fire(ModeEvent.HEADING_SEARCH)  # and _reset restarts the hypotheses
            what += "; the heading searched for again"
        if again:
            self._relevel()
            what += "; still refused after the last reset: attitude levelled again"
        if not self.heading_aligned:
            self._forget_heading()
        self._init_position(fix)
        covariance.reinitialise(state.cov, V, np.eye(3) * self.options.init.sigma_velocity_moving**2)
        self._reset(fix.t_ns, "gps_rejected", f"every GPS fix rejected for {after_s:g} s; {what}")

    def _relevel(self) -> None:
        """The attitude starts again level at its last heading (a helicopter in cruise is within a few
        degrees of level; a corrupted attitude may be upside down, beyond what an update can pull
        back), with a moving start's sigma; the heading becomes unknown."""
        state = self.state
        state.q = quat_from_euler(0.0, 0.0, float(yaw_of(state.q)))
        self.modes.fire(ModeEvent.RELEVEL)
        sigma = math.radians(self.options.init.sigma_attitude_moving_deg)
        covariance.reinitialise(state.cov, TH, np.diag([sigma**2, sigma**2, 0.0]))
        self._forget_heading()
        self._level_sum, self._level_n, self._level_t0 = np.zeros(3), 0, state.t_ns

    def _reset_camera_lost(self, t_ns: int, why: str) -> None:
        """The camera's innovations say the filter is lost: map cleared, velocity, attitude and biases
        re-initialised as for a start in motion. In the camera's own frame with a visual start at hand, the
        filter is dropped instead (nothing else places it): the visual-inertial start begins again and
        continues the frame where this one was lost."""
        state, own_frame = self.state, self.mode is FilterMode.LOCAL and self.visual_inertial is not None
        self._reset(t_ns, "camera_lost", f"camera innovations out of band for {self.options.health.innovation_reset_s:g} s "
                    f"({why}): map cleared, " + ("the filter dropped until the visual-inertial start" if own_frame
                                                 else "velocity, attitude and biases re-initialised"))
        if own_frame:
            self._starter.hold_gauge(state)
            self.modes.fire(ModeEvent.CAMERA_LOST)
            self.state = None
            self.visual_inertial.reset()
            return
        state.robot_only(self._reset_covariance(covariance.block_variances(state.cov, covariance.P)))
        if not self.heading_aligned:
            self._forget_heading()
        if self.position_initialized and self._last_fix is not None and self.health.fresh("gps", t_ns):
            self._init_position(self._last_fix)

    # ------------------------------------------------------------------------------ camera
    def process_features(self, features: FrameFeatures) -> FrameReport:
        """Fuse one frame's features at its own time (EKF-SLAM, ``vtolpose.estimator.vision.camera_pipeline``).

        Bad frames are counted under ``camera`` by reason; landmark-level outcomes (matched,
        rejected by gate, ratio, χ², behind the camera) under ``camera_match``.
        """
        counts = self.counts.setdefault("camera", RejectionCounts())
        counts.received += 1
        t_ns = features.t_ns  # already on the IMU clock (the runtime applies camera.time_offset_s)
        reason = self._frame_rejection(features, t_ns)
        self._last_frame = (t_ns, features.digest) if reason != "out_of_order" else self._last_frame
        if reason in (None, "before_start") and self._visual_start_pending():
            return self._visual_start_frame(features, counts)
        if reason == "before_start" and self.visual_inertial is not None:
            self.visual_inertial.observe(features)  # does the scene move? (a cruise feels still to the IMU)
        if reason is None and self._heading_weak():
            reason = "heading_weak"
        if reason is None and self.state.n_landmarks == 0 and self._tilt_weak():
            reason = "tilt_weak"
        if reason is None and self._moving_start and not (self.heading_aligned or self.local_position):
            reason = "heading_unknown"  # the bank places it from the GPS first
        if reason is not None:
            counts.reject(reason)
            self.health.measured("camera", t_ns, used=False)  # alive (frames arrive), not usable
            return FrameReport(t_ns, False, reason, n_features=len(features))
        self._propagate_to(t_ns)
        self.camera.attach_calibration(self.state)  # the time offset's state, if estimated and not there yet
        # Before the heading is known, landmarks live in the frame of arbitrary yaw with the rest of the
        # camera geometry (consistent with itself, so only the heading is held) and go when it is placed:
        # at rest on the pad the camera holds the pose from the first frames.
        held = None
        if not self.heading_aligned:
            held = np.zeros(self.state.dim, dtype=bool)
            held[YAW] = True
        report = self.camera.process(self.state, features, t_ns, True, self.position_initialized, held,
                                     self._gyro - self.state.b_g)
        if report.accepted:
            counts.used += 1
            if self.mode is FilterMode.UNREFERENCED and not self._gps_seen:
                self.modes.fire(ModeEvent.CAMERA_USED)  # the camera's own frame from now on
        else:
            counts.reject(report.reason)
        self.health.measured("camera", t_ns, report.accepted)
        lost, why = self.health.camera_frame(FrameInnovations(
            t_ns, report.candidates, report.n_matches, len(report.new_ids), report.nis, 2 * report.n_matches))
        if lost:
            self._reset_camera_lost(t_ns, why)
        matches = self.counts.setdefault("camera_match", RejectionCounts())
        matches.received += report.candidates
        matches.used += report.n_matches
        for why, n in report.match_rejections.items():
            matches.reject(why, n)
        if report.behind_camera:
            matches.flag("behind_camera", report.behind_camera)
        return report

    def _visual_start_frame(self, features: FrameFeatures, counts: RejectionCounts) -> FrameReport:
        """A frame for the visual-inertial start (the IMU brought to its time first); the start once it converges."""
        t_ns = features.t_ns
        for delta in (self._downsampler.flush(), self._downsampler.hold(t_ns, self._next_sample(t_ns))):
            if delta is not None:
                self.visual_inertial.add_delta(delta)
        clock = self.camera.time_offset
        if clock.options.estimate:  # the window solves the offset too, from what the filter knows of it
            self.visual_inertial.set_time_offset_prior(clock.value_s, math.sqrt(clock.variance))
        start = self.visual_inertial.add_frame(features, self._starter.gauge())
        self.health.measured("camera", t_ns, used=True)  # alive and in use, by the start
        if start is None:
            counts.reject("initialising")
            return FrameReport(t_ns, False, "initialising", n_features=len(features))
        self._apply_visual_start(start)
        counts.used += 1
        return FrameReport(t_ns, True, "visual-inertial start", n_features=len(features), n_landmarks=len(start.landmarks))

    def _heading_weak(self) -> bool:
        """The bank placed the heading, but it is still tens of degrees uncertain: the camera waits. A map
        started under such a heading grows overconfident in it (and in the tilt) faster than the GPS
        corrects it (a flight joined in the air ends 7-9 sigma off); the IMU and GPS narrow it alone. Before the
        placement, after a start in motion, the camera waits too: a map in the frame of arbitrary yaw, with the
        horizontal acceleration misplaced by the unknown heading, would refuse the GPS in a cruise."""
        return (self.heading_mode is HeadingMode.PLACED
                and self.state.cov[YAW, YAW] > HEADING_WEAK_SIGMA_RAD**2)

    def _tilt_weak(self) -> bool:
        """A map started under a tilt still degrees uncertain is placed wrongly by it, and its first updates
        then narrow the heading the camera cannot see: the camera waits for gravity to narrow the tilt."""
        var = covariance.block_variances(self.state.cov, TH)
        return max(var[0], var[1]) > TILT_WEAK_SIGMA_RAD**2

    def _frame_rejection(self, features: FrameFeatures, t_ns: int) -> str | None:
        if self.camera is None:
            return "no_camera_calibration"
        if features.problem is not None:
            return features.problem
        cam = self.camera.calibration  # the working size: the frame as the features were found on it
        if tuple(features.image_shape) != (cam.height, cam.width):
            return "wrong_size"
        last = self._last_frame
        if last is not None and t_ns <= last[0]:
            return "out_of_order"
        if last is not None and features.digest and features.digest == last[1]:
            return "duplicate"
        if self.state is None:
            return "before_start"
        if t_ns < self.state.t_ns:
            return "older_than_filter"
        if self._position_pending(t_ns):
            return "position_pending"
        return None

    def _position_pending(self, t_ns: int) -> bool:
        """Started with a GPS heard, its first fix since still to come (and not overdue). A map made now is
        placed around the vehicle where the filter has it before any fix, and that fix moves the vehicle, not
        the map: the next frame reads the jump (a metre, on the camera matrix) as a baseline never flown, and
        its iterated update bends the depths, the attitude and an estimated mounting to explain it (φ_z −6°
        in one frame). The first fix comes within the GPS's period; a GPS gone quiet lets the camera in."""
        return (self.mode is FilterMode.UNREFERENCED and self._gps_heard_ns is not None
                and (t_ns - self._gps_heard_ns) * 1e-9 <= self.options.health.gps_stale_s)

    # ------------------------------------------------------------------- rest and levelling
    def _level(self, t_ns: int, accel: np.ndarray) -> None:
        """Before the heading is known: mean specific force as a gravity reference for roll/pitch."""
        self._level_sum += accel
        self._level_n += 1
        if (t_ns - self._level_t0) * 1e-9 < self.options.level_interval_s:
            return
        f_mean = self._level_sum / self._level_n
        self._level_sum, self._level_n, self._level_t0 = np.zeros(3), 0, t_ns
        self._apply_level(f_mean)

    def _level_run(self, t_arr: np.ndarray, accel: np.ndarray) -> dict[int, np.ndarray]:
        """:meth:`_level`'s sums for a run (compiled): each ended interval's mean, by its last sample's index."""
        sums, state = np.array(self._level_sum, dtype=float), np.array([self._level_n, self._level_t0], np.int64)
        ends, means = level_run(t_arr, accel, sums, state, self.options.level_interval_s)
        self._level_sum, self._level_n, self._level_t0 = sums, int(state[0]), int(state[1])
        return dict(zip(ends.tolist(), means))

    def _apply_level(self, f_mean: np.ndarray) -> None:
        """One levelling update from an interval's mean specific force."""
        counts = self.counts["level"]
        counts.received += 1
        # Only roll, pitch and the gyro bias may move: the heading is invisible to gravity, and
        # position and velocity must not absorb the vehicle's own accelerations.
        held = np.ones(self.state.dim, dtype=bool)
        held[TH.start : YAW] = False
        if self.layout.estimates_biases:
            held[self.layout.BG] = False
        outcome = self._leveller.update(self.state, f_mean, held)
        if outcome.accepted:
            counts.used += 1
        else:
            counts.reject(outcome.reason.replace(" ", "_"))

    def _apply_still(self, chunk: StillChunk) -> None:
        """Zero-velocity update and a gyro-bias measurement from a still chunk."""
        counts = self.counts["still"]
        counts.received += 1
        state = self.state
        # Zero velocity holds in any frame, that of arbitrary yaw included: it may correct tilt and
        # biases before the heading is known (the heading itself is uncorrelated with them then).
        sigma = self.options.still.zupt_sigma
        gauge = heading_gauge(state)
        zupt = ekf_update(state, slice(3, 6), np.eye(3), -state.v, np.eye(3) * sigma**2, chi2_gate(3, 0.999))
        if not zupt.accepted:
            counts.reject(f"zupt_{zupt.reason.replace(' ', '_')}")
            return
        counts.used += 1
        self._accel_at_rest = self._horizontal_accel.copy()
        # The mean rate of a still IMU is its bias; its variance is what the samples' scatter says,
        # never less than the white-noise density allows over the chunk.
        r = np.maximum(chunk.gyro_var_of_mean, self.noise.gyro_noise_density**2 / chunk.duration_s)
        if self._bank is not None:
            self._bank.at_rest(chunk.gyro_mean, r, sigma)
        if self.layout.estimates_biases:
            ekf_update(state, self.layout.BG, np.eye(3), chunk.gyro_mean - state.b_g, np.diag(r))
        else:
            # Thesis model: the bias is a calibration constant; refine it as a per-axis
            # weighted mean, the older value aged by the bias random walk.
            prior = self._fixed_bias_var + self.noise.gyro_random_walk**2 * chunk.duration_s
            gain = prior / (prior + r)
            state.b_g = state.b_g + gain * (chunk.gyro_mean - state.b_g)
            self._fixed_bias_var = (1.0 - gain) * prior
        carry_gauge(state, gauge)  # the map's heading gauge follows the move (camera_update.carry_gauge)

    # ------------------------------------------------------------------------------ output
    def _event(self, t_ns: int, kind: EventKind, message: str, reset_kind: str | None = None, **figures: float) -> None:
        self.events.append(EstimatorEvent(t_ns, kind, message, self.reset_counter, reset_kind, MappingProxyType(figures)))

    def count_refused_imu(self, reason: str, n: int = 1) -> None:
        """IMU samples the caller refused before they reached the filter (out of the sensor's range): counted
        with the filter's own, so a report shows them beside the rest."""
        counts = self.counts["imu"]
        counts.received += n
        counts.reject(reason, n)

    def status(self) -> EstimatorStatus:
        """A frozen snapshot of what the service may know (modes, counters, health, events, map size)."""
        state, camera, visual = self.state, self.camera, self.visual_inertial
        t_ns = state.t_ns if state is not None else None
        waiting = visual is not None and visual.progress is not None and state is None
        heading_sigma = None if state is None else math.degrees(math.sqrt(self.published_cov9()[YAW, YAW]))
        return EstimatorStatus(
            t_ns=t_ns, mode=self.mode, heading=self.heading_mode, reset_counter=self.reset_counter,
            heading_sigma_deg=heading_sigma, heading_placement=self.heading_placement, started_moving=self._moving_start,
            counts=MappingProxyType(self.counts_report()), health=MappingProxyType(self.health.report(t_ns)),
            events=tuple(self.events),
            gyro_bias=None if state is None else tuple(float(x) for x in state.b_g),
            accel_bias=None if state is None else tuple(float(x) for x in state.b_a),
            landmarks=0 if state is None else state.n_landmarks,
            landmarks_initialised=camera.initialized_total if camera is not None else 0,
            landmarks_deleted=MappingProxyType(dict(sorted(camera.deleted_total.items())) if camera is not None else {}),
            visual_start_waiting=visual.progress if waiting else None,
            visual_start_history=tuple(visual.history) if visual is not None else (),
            visual_start_attempts=visual.attempts if visual is not None else 0,
            gps_noise=MappingProxyType(self.gps_noise.report()),
            camera_time_offset_s=camera.time_offset.reading(state) if camera is not None else None,
            camera_mounting=camera.mounting.reading(state) if camera is not None else None,
        )

    def finish_recording(self) -> None:
        """The end of the data: the recorder closes its last segment on the final state."""
        if self.recorder is not None:
            self.recorder.finish(self.state, self.heading_aligned)

    def map_ids(self) -> np.ndarray:
        """The ids of the map's landmarks, in the state's order."""
        return self.camera.book.ids if self.camera is not None else np.zeros(0, np.int64)

    def map_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Ids and world points of the map's landmarks that lie ahead of their anchor (positive inverse depth)."""
        state, camera = self.state, self.camera
        if state is None or camera is None or state.n_landmarks == 0:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        y = state.landmarks
        ahead = y[:, INVERSE_DEPTH] > 0.0
        return camera.book.ids[ahead], landmark_points(y[ahead])

    def counts_report(self) -> dict:
        return {name: c.as_dict() for name, c in self.counts.items()}
