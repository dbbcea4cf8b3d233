"""Fusion order: a delayed fusion horizon over buffered IMU samples, and an output predictor.

Measurements arrive late (a camera frame needs tens of milliseconds of feature extraction, a
GPS fix comes through a serial link) but must be fused at their own timestamps, in time order
with the IMU. As in PX4's EKF2, the filter runs on a *delayed* time horizon, ``delay_s`` behind
the newest IMU sample: IMU samples wait in a short buffer, measurements wait in a heap, and
both are handed to the estimator in time order once the horizon passes them (IMU first at
equal times, then measurements in arrival order). A measurement older than what the filter
has already consumed is counted as ``too_late`` and dropped.

The published pose must not lag by the delay, so an *output predictor* propagates the delayed
state's nominal values (position, velocity, attitude; biases held) through the buffered IMU
samples to the newest one, one sample at a time. When the delayed state is corrected (a
measurement, a levelling or stillness update, a reset) the prediction is recomputed from it;
otherwise it simply advances with each new sample. Its covariance is the delayed covariance
grown over the prediction interval by the IMU noise and the velocity and attitude
uncertainty. Everything here is deterministic: the same inputs give the same outputs, so a
replay through the runtime equals the offline replay.
"""

from __future__ import annotations

import heapq
from bisect import bisect_left, bisect_right
import math
from collections import deque
from dataclasses import dataclass, replace
from operator import itemgetter, lt
from itertools import chain, islice
from typing import Any, Callable

import numpy as np

from vtolpose.estimator.filter import Estimator, published_cov9
from vtolpose.estimator.core.measurements import ImuSample, RejectionCounts, readings_finite, rows_finite
from vtolpose.estimator.inertial.propagator import is_isotropic, noise_dt_polynomial, process_noise
from vtolpose.estimator.inertial.imu_delta import reading_between
from vtolpose.estimator.core.rotation import quat_product, rot_of, rotate, rotvec_quat, skew
from vtolpose.estimator.core.covariance import BG
from vtolpose.estimator.core.state import StateLayout

_RESYNC_NS = 1_000_000_000  # re-anchor the prediction at least this often (numerical drift only)
# A run's fixed cost (its compiled passes over the samples) is that of a few samples one by one: shorter
# stretches, such as the one sample a horizon moved by, go one sample at a time (the results are the same).
MIN_RUN = 4
_ROBOT9 = StateLayout("thesis")  # p, v, θ: the blocks the predictor's covariance covers
_POSE_FLAT = (np.r_[0:3, 6:9][:, None] * 9 + np.r_[0:3, 6:9][None, :]).ravel()  # [δp, δθ] entries of a flat 9 × 9


def _sliceable(t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> bool:
    """Whether slices of a batch's rows are what stacking them gives (C-ordered float rows of 3, int64 times):
    the compiled runs take them as they are, without compiling for another layout."""
    return (t_ns.dtype == np.int64 and gyro.dtype == accel.dtype == np.float64 and gyro.ndim == accel.ndim == 2
            and gyro.shape[1] == accel.shape[1] == 3 and gyro.flags.c_contiguous and accel.flags.c_contiguous)


def _pose_cov(cov9: np.ndarray) -> np.ndarray:
    """cov9's position and attitude blocks (6 × 6): one take on precomputed indices (cheaper than np.ix_)."""
    return cov9.take(_POSE_FLAT).reshape(6, 6)


Apply = Callable[[Estimator], Any]
# At equal time stamps measurements fuse in the streams' order (GPS, then camera, then the rest), whichever
# arrived first: a replay that hands frames over early (their features ready sooner) fuses as one that does not.
_KIND_RANK = {"gps": 0, "camera": 1}


@dataclass(slots=True)
class FusionOptions:
    delay_s: float = 0.15  # the fusion horizon lags the newest IMU sample by this much
    max_pending: int = 64  # measurements waiting for the horizon; more are refused and counted
    max_imu_buffer: int = 4096  # IMU samples ahead of the horizon; beyond it the oldest are fused early
    predict: bool = True  # keep the output predictor; off when nobody reads the present pose (offline replay)

    def __post_init__(self) -> None:
        if not (self.delay_s >= 0.0 and math.isfinite(self.delay_s)):
            raise ValueError(f"fusion delay must be >= 0 s, got {self.delay_s}")
        if self.max_pending < 1 or self.max_imu_buffer < 1:
            raise ValueError("fusion buffer limits must be at least 1")


@dataclass(slots=True)
class OutputPose:
    """A published estimate: world NED, body→world attitude (w first), body angular rate.

    ``cov9`` is the covariance of ``[δp, δv, δθ]`` with the attitude error in the world frame
    (``R_true = Exp(δθ) R``); ``omega_var`` the variance of the body rates. ``fused_t_ns`` is the
    time of the delayed (fused) state this pose was predicted from; equal to ``t_ns`` when the
    pose is the fused state itself. A value, never changed once made (not frozen: one is made for
    every fused step and every published pose, and a frozen one costs three times as much to make).
    """

    t_ns: int
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    omega_b: np.ndarray
    cov9: np.ndarray
    pose_cov: np.ndarray  # 6 × 6 over [δp, δθ] (world-frame attitude error): cov9's position and attitude blocks
    omega_var: np.ndarray
    heading_aligned: bool
    position_initialized: bool
    reset_counter: int
    fused_t_ns: int
    quality_cap: int = 100  # ceiling on the published quality from the filter's health (estimator.health)
    local_position: bool = False  # no absolute position: relative to the filter's own origin (camera, no GPS)

    @property
    def fused(self) -> bool:
        return self.t_ns == self.fused_t_ns


@dataclass(slots=True)
class FusedRun:
    """The fused poses of consecutive filter steps that only propagated, as arrays (a row per step): what an
    offline replay records without making an :class:`OutputPose` per step. The published covariances are
    worked out when asked for (:meth:`cov9`, :meth:`pose_cov`: a recorder wants one now and then), and so are
    the body rates and their variance (:meth:`omega_b`, :meth:`omega_var`: from values kept here, never changed);
    :meth:`poses` makes the poses, equal to the ones the steps one by one would have made."""

    t_ns: np.ndarray
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    gyro: np.ndarray  # the samples of the run the steps came from
    gyro_rows: list[int]  # each step's last sample among them
    b_g: np.ndarray  # the gyro bias over the steps (the state's; the filter replaces it, never changes it in place)
    robot_cov: np.ndarray  # the filter's robot covariance after each step (never changed)
    white_rate_var: np.ndarray  # the gyro's white-noise rate variance, per axis
    estimates_biases: bool  # the state's layout: the bias's variance adds to the rates'
    heading_aligned: bool
    position_initialized: bool
    reset_counter: int
    quality_cap: list[int]
    local_position: bool
    local_heading_floor: float | None  # Estimator.local_heading_floor

    def __len__(self) -> int:
        return len(self.t_ns)

    def cov9(self) -> np.ndarray:
        """Each step's published ``[δp, δv, δθ]`` covariance (``OutputPose.cov9``), stacked."""
        return published_cov9(self.robot_cov, self.heading_aligned, self.local_heading_floor)

    def pose_cov(self, x: int) -> np.ndarray:
        """Step ``x``'s ``OutputPose.pose_cov``."""
        return _pose_cov(published_cov9(self.robot_cov[x], self.heading_aligned, self.local_heading_floor))

    def omega_b(self) -> np.ndarray:
        """Each step's body rates (``OutputPose.omega_b``): its last gyro reading less the bias."""
        return self.gyro[self.gyro_rows] - self.b_g

    def omega_var(self) -> np.ndarray:
        """Each step's ``OutputPose.omega_var``."""
        if self.estimates_biases:
            return self.white_rate_var + self.robot_cov.diagonal(axis1=1, axis2=2)[:, BG]
        return np.tile(self.white_rate_var, (len(self.t_ns), 1))

    def poses(self) -> list[OutputPose]:
        cov9 = self.cov9()
        pose_cov = cov9.reshape(len(cov9), 81)[:, _POSE_FLAT].reshape(len(cov9), 6, 6)
        flags = (self.heading_aligned, self.position_initialized, self.reset_counter)
        return [OutputPose(t, p, v, q, w, c9, pc, ov, *flags, t, cap, self.local_position)
                for t, p, v, q, w, c9, pc, ov, cap in zip(self.t_ns.tolist(), self.p, self.v, self.q, self.omega_b(),
                                                          cov9, pose_cov, self.omega_var(), self.quality_cap)]


def nominal_step(
    p: tuple, v: tuple, q: tuple, b_g: tuple, b_a: tuple,
    g0: tuple, a0: tuple, g1: tuple, a1: tuple, dt: float, gravity_down: float,
) -> tuple[tuple, tuple, tuple]:
    """One IMU sample step of the nominal state, in scalars (it runs for every sample).

    The same arithmetic as a one-sample :class:`~vtolpose.estimator.inertial.imu_delta.ImuDelta` (trapezoid rates,
    specific force rotated by the half-step) followed by
    the propagator's nominal integration (``tests/propagation_oracle.py``); a test holds the two together.
    """
    # Raw increments over the step.
    wx, wy, wz = 0.5 * dt * (g0[0] + g1[0]), 0.5 * dt * (g0[1] + g1[1]), 0.5 * dt * (g0[2] + g1[2])
    fx, fy, fz = 0.5 * dt * (a0[0] + a1[0]), 0.5 * dt * (a0[1] + a1[1]), 0.5 * dt * (a0[2] + a1[2])
    hw, hx, hy, hz = rotvec_quat(0.5 * wx, 0.5 * wy, 0.5 * wz)
    dvx, dvy, dvz = rotate(hw, hx, hy, hz, fx, fy, fz)
    # Bias correction (first order, as in the propagator).
    bx, by, bz = b_g
    px, py, pz = wx - bx * dt, wy - by * dt, wz - bz * dt
    h = 0.5 * dt
    kx, ky, kz = by * dvz - bz * dvy, bz * dvx - bx * dvz, bx * dvy - by * dvx
    sx, sy, sz = (dvx - h * kx) / dt - b_a[0], (dvy - h * ky) / dt - b_a[1], (dvz - h * kz) / dt - b_a[2]
    r0, r1, r2 = rot_of(*q)
    ax = r0[0] * sx + r0[1] * sy + r0[2] * sz
    ay = r1[0] * sx + r1[1] * sy + r1[2] * sz
    az = r2[0] * sx + r2[1] * sy + r2[2] * sz
    az += gravity_down
    hh = 0.5 * dt * dt
    p_new = (p[0] + v[0] * dt + hh * ax, p[1] + v[1] * dt + hh * ay, p[2] + v[2] * dt + hh * az)
    v_new = (v[0] + ax * dt, v[1] + ay * dt, v[2] + az * dt)
    nw, nx, ny, nz = quat_product(*q, *rotvec_quat(px, py, pz))
    norm = 1.0 / math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
    return p_new, v_new, (nw * norm, nx * norm, ny * norm, nz * norm)


@dataclass(slots=True)
class _Prediction:
    """The nominal state propagated to ``t_ns`` (tuples of floats: it is updated every sample)."""

    t_ns: int
    p: tuple
    v: tuple
    q: tuple
    gyro: np.ndarray  # the latest sample's readings (the next step's trapezoid starts from them)
    accel: np.ndarray
    anchor_t_ns: int
    signature: tuple
    floats: tuple = ()  # (gyro, accel) as tuples of floats, once a step has made them


def _step_prediction(pred: _Prediction, t: int, gyro: np.ndarray, accel: np.ndarray, b_g: tuple, b_a: tuple,
                     gravity_down: float, gap_needs_reset: Callable[[float], bool]) -> None:
    """The output predictor's step to the sample at ``t`` (biases as floats); over a gap the filter would reset
    for (``HealthMonitor.gap_needs_reset``), the prediction holds (as the filter does: it does not fly through a hole)."""
    if t <= pred.t_ns:
        return
    if gap_needs_reset((t - pred.t_ns) * 1e-9):
        pred.t_ns, pred.gyro, pred.accel, pred.floats = t, gyro, accel, ()
        return
    g0, a0 = pred.floats or (tuple(pred.gyro.tolist()), tuple(pred.accel.tolist()))
    g1, a1 = tuple(gyro.tolist()), tuple(accel.tolist())
    pred.p, pred.v, pred.q = nominal_step(pred.p, pred.v, pred.q, b_g, b_a, g0, a0, g1, a1, (t - pred.t_ns) * 1e-9,
                                          gravity_down)
    pred.t_ns, pred.gyro, pred.accel, pred.floats = t, gyro, accel, (g1, a1)


@dataclass(slots=True)
class DetachedPrediction:
    """The output predictor cut loose from the filter while the filter is busy elsewhere (a camera update on
    another thread): it steps its own copy of the prediction with the biases, gravity and flags of the moment
    it was made (:meth:`FusionCore.detached`), and hands out that moment's covariance, not grown meanwhile
    (the filter is back within tens of milliseconds and the prediction is then made again from it)."""

    pred: _Prediction
    b_g: np.ndarray
    bias_floats: tuple  # (b_g, b_a) as tuples of floats
    gravity_down: float
    gap_needs_reset: Callable[[float], bool]  # the health monitor's (it reads only its options)
    covariance: tuple  # (cov9, pose_cov, omega_var)
    flags: tuple  # OutputPose's fields from heading_aligned on

    def step(self, t: int, gyro: np.ndarray, accel: np.ndarray) -> None:
        _step_prediction(self.pred, t, gyro, accel, *self.bias_floats, self.gravity_down, self.gap_needs_reset)

    def output(self) -> OutputPose:
        pred = self.pred
        return OutputPose(pred.t_ns, np.array(pred.p), np.array(pred.v), np.array(pred.q), pred.gyro - self.b_g,
                          *self.covariance, *self.flags)


class FusionCore:
    """Feeds an :class:`Estimator` in time order on a delayed horizon; predicts the present.

    ``on_fused(pose)`` is called after every IMU sample the estimator consumed that advanced its
    state (the same rule as the offline replay's recorder), with the fused pose; ``on_fused_run(run)``, if
    given, in its place with the poses of a run's compiled steps at once (:class:`FusedRun`).
    """

    def __init__(
        self,
        estimator: Estimator,
        options: FusionOptions | None = None,
        on_fused: Callable[[OutputPose], None] | None = None,
        on_fused_run: Callable[[FusedRun], None] | None = None,
    ) -> None:
        self.est = estimator
        self.options = opts = options or FusionOptions()
        self.delay_ns = int(round(opts.delay_s * 1e9))
        self.on_fused = on_fused
        self.on_fused_run = on_fused_run
        self.predict = opts.predict  # the runtime turns it off when it has no outputs
        self.counts: dict[str, RejectionCounts] = {"imu": RejectionCounts()}
        self._queue: deque[tuple[int, np.ndarray, np.ndarray, bool]] = deque()  # not yet fused
        # The arrays of batches added whole (times, gyro, accel) while samples of theirs may be queued: a run
        # within one of them is a slice of its arrays rather than its queued rows stacked again.
        self._batches: deque[tuple[np.ndarray, np.ndarray, np.ndarray]] = deque()
        self._recent: deque[tuple[int, np.ndarray, np.ndarray]] = deque()  # fused, newer than the filter state
        self._pending: list[tuple[int, int, int, str, Apply]] = []  # (t_ns, kind's rank, arrival, kind, apply)
        self._seq = 0
        self._newest_t: int | None = None
        self._refused: tuple[int, int] | None = None  # stamps spanned by the current run of refused IMU samples
        self._discontinuities: dict[int, float] = {}  # sample time -> seconds of data lost just before it
        self._fused_until: int | None = None
        self._last_reported_t: int | None = None
        self._pred: _Prediction | None = None
        self._measured = False  # a measurement was applied since the prediction was anchored
        self._F = np.eye(9)
        self._eye3 = np.eye(3)
        self._q_terms: tuple | None = None
        self._white_rate_var: tuple | None = None  # (noise, rate, the gyro's white-noise rate variance) of _omega_var
        self._bias_floats: tuple = (None, None, (), ())  # (b_g, b_a, their floats): the state replaces, never changes them
        self._out_cov: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # see output()

    # ---------------------------------------------------------------------------- inputs
    def add_imu(self, sample: ImuSample, fuse: bool = True) -> bool:
        """Buffer a sample and advance the prediction to it; with ``fuse``, then :meth:`advance`.

        A runtime that must publish first calls ``add_imu(s, fuse=False)``, ``output()``, publishes,
        and only then :meth:`advance`: the delayed filter's work never delays the pose. False: refused.
        """
        t = sample.t_ns
        counts = self.counts["imu"]
        counts.received += 1
        if self._newest_t is not None and t <= self._newest_t:
            counts.reject("time_not_increasing")
            low, high = self._refused or (t, t)
            self._refused = (min(low, t), max(high, t))
            return False
        if self._refused is not None:
            # A run of samples stamped in the past (a backward clock step): the time they span
            # passed for the vehicle but not for the filter. The estimator widens for it at this sample.
            self._discontinuities[t] = (self._refused[1] - self._refused[0]) * 1e-9
            self._refused = None
        counts.used += 1
        gyro, accel = sample.gyro, sample.accel
        finite = readings_finite(gyro, accel)
        self._queue.append((t, gyro, accel, finite))
        self._newest_t = t
        if self._pred is not None and finite and self.predict:
            self._step(self._pred, t, gyro, accel)
        if fuse:
            self.advance()
        return True

    def add_imu_batch(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray,
                      finite: np.ndarray | None = None) -> None:
        """Samples in time order (rows), exactly as :meth:`add_imu` with ``fuse`` for each in turn.

        With no prediction to keep, nothing between two samples reads the state, so the checks run on
        the whole batch and the horizon is advanced once, past the last sample: the estimator sees the
        same calls in the same order. ``finite``: each row's ``readings_finite``, if already known. A batch that needs the per-sample rules (a prediction, a clock
        step back, a buffer about to overflow) goes through :meth:`add_imu` one sample at a time.
        """
        n = len(t_ns)
        if n == 0:
            return
        times = t_ns.tolist()
        newest = self._newest_t
        if (self.predict or self._refused is not None or len(self._queue) + n > self.options.max_imu_buffer
                or (newest is not None and times[0] <= newest) or not all(map(lt, times, islice(times, 1, None)))):
            for t, g, a in zip(times, gyro, accel):
                self.add_imu(ImuSample(t, g, a))
            return
        counts = self.counts["imu"]
        counts.received += n
        counts.used += n
        finite = rows_finite(gyro, accel) if finite is None else finite  # the caller's, if it screened the rows
        self._queue.extend(zip(times, gyro, accel, finite.tolist()))
        self._forget_batches_before(self._queue[0][0])  # none of their samples queued any more
        if _sliceable(t_ns, gyro, accel):
            self._batches.append((t_ns, gyro, accel))
        self._newest_t = times[-1]
        self.advance()

    def advance(self) -> None:
        """Fuse what the horizon has passed; re-anchor the prediction if the filter was corrected."""
        if self._newest_t is None:
            return
        self._advance(self._newest_t - self.delay_ns)
        counts = self.counts["imu"]
        while len(self._queue) > self.options.max_imu_buffer:
            counts.flag("horizon_forced")
            self._advance(self._queue[0][0])
        if not self.predict:
            return
        pred = self._pred
        if pred is None or not self._prediction_current(pred):
            self._pred = self._repredict()
        # The next outputs' covariance, computed now that the pose has left (off the pose path).
        self._out_cov = self._predicted_covariance() if self._pred is not None else None

    def add_measurement(self, t_ns: int, apply: Apply, kind: str, fuse_now: bool = True) -> bool:
        """Queue ``apply(estimator)`` to run when the horizon reaches ``t_ns``. False: refused (counted).
        ``fuse_now``: one the horizon has passed already is fused at once; otherwise at the next :meth:`advance`."""
        counts = self.counts.setdefault(kind, RejectionCounts())
        counts.received += 1
        if self._fused_until is not None and t_ns < self._fused_until:
            counts.reject("too_late")
            return False
        if len(self._pending) >= self.options.max_pending:
            counts.reject("buffer_full")
            return False
        heapq.heappush(self._pending, (int(t_ns), _KIND_RANK.get(kind, 2), self._seq, kind, apply))
        self._seq += 1
        if fuse_now and self._newest_t is not None and t_ns <= self._newest_t - self.delay_ns:
            self._advance(self._newest_t - self.delay_ns)  # already behind the horizon: fuse it now
            self._pred = self._repredict() if self.predict else None
            self._out_cov = None
        return True

    def flush(self) -> None:
        """Fuse everything buffered (end of a replay, shutdown): the filter catches up with the present."""
        self._advance(np.iinfo(np.int64).max, hold=False)
        self._out_cov = None

    # --------------------------------------------------------------------------- fusing
    def _advance(self, horizon: int, hold: bool = True) -> None:
        """Fuse in time order up to ``horizon``. Without a prediction nobody reads the state before the next
        call, so a run that would end at the horizon (no measurement in it) may be ``hold``-ed: its samples
        wait and are fused with the next stretch as one run, once — half as many runs, the same calls in
        the same order (a run is bit for bit its samples one by one). What the horizon passed still
        counts as fused for a measurement arriving too late, as if it had been."""
        queue, pending, est = self._queue, self._pending, self.est
        while queue or pending:
            t_imu = queue[0][0] if queue else None
            t_meas = pending[0][0] if pending else None
            if t_imu is not None and (t_meas is None or t_imu <= t_meas):
                if t_imu > horizon:
                    return
                until = min(horizon, t_meas) if t_meas is not None else horizon
                if (not self.predict and not self._discontinuities and len(queue) >= MIN_RUN
                        and queue[MIN_RUN - 1][0] <= until and est.takes_runs):
                    if (hold and (t_meas is None or t_meas > horizon)
                            and (self._fused_until is None or t_imu > self._fused_until)):
                        self._fused_until = self._last_time_until(horizon)
                        return
                    self._fuse_run(until)
                    continue
                self._fuse_one_imu()
            else:
                if t_meas > horizon:
                    return
                t, _, _, kind, apply = heapq.heappop(pending)
                self._fused_until = max(t, self._fused_until or t)
                est.imu_ahead(self._sample_after())
                apply(est)
                est.imu_ahead(None)
                self.counts[kind].used += 1
                self._measured = True

    def _sample_after(self) -> tuple[int, np.ndarray, np.ndarray] | None:
        """The next buffered IMU sample, for a measurement about to be applied (the samples up to it are fused):
        the estimator interpolates the reading to the measurement's time. The horizon lags the newest sample,
        so one is there unless the buffer is flushed past it; None too if the estimator will refuse it (not
        finite) or widen for time lost before it."""
        if not self._queue:
            return None
        t, gyro, accel, finite = self._queue[0]
        return (t, gyro, accel) if finite and t not in self._discontinuities else None

    def _last_time_until(self, horizon: int) -> int:
        """The time of the last buffered IMU sample at or before ``horizon`` (there is one; the times increase)."""
        return self._queue[bisect_right(self._queue, horizon, key=itemgetter(0)) - 1][0]

    def _fuse_one_imu(self) -> None:
        """The oldest buffered IMU sample into the estimator; the fused pose if it advanced the state."""
        est = self.est
        t, gyro, accel, finite = self._queue.popleft()
        self._fused_until = t
        if self._discontinuities:
            lost_s = self._discontinuities.pop(t, None)
            if lost_s is not None:
                est.imu_discontinuity(lost_s)
        ok = est.process_imu(t, gyro, accel)
        if finite:
            self._recent.append((t, gyro, accel))
        state = est.state
        recent = self._recent
        if state is None:  # not started: nothing to predict from, keep only the latest reading
            while len(recent) > 1:
                recent.popleft()
            return
        while len(recent) > 1 and recent[1][0] <= state.t_ns:
            recent.popleft()
        if ok and (self._last_reported_t is None or state.t_ns > self._last_reported_t):
            self._last_reported_t = state.t_ns
            if self.on_fused is not None:
                self.on_fused(self._fused_pose(gyro))

    def _fuse_run(self, until: int) -> None:
        """The IMU samples up to ``until`` (the next measurement or the horizon) as one run for
        :meth:`Estimator.process_imu_run`, with the fused pose after each step as sample by sample;
        sample by sample (the loop above) if the estimator declines the run."""
        queue, est = self._queue, self.est
        run = []
        while queue and queue[0][0] <= until:
            run.append(queue.popleft())
        rows = self._batch_rows(run[0][0], run[-1][0], len(run))
        if rows is not None:
            t_arr, gyro, accel = rows
            times = t_arr.tolist()
        else:
            times = [item[0] for item in run]
            t_arr, gyro, accel = np.array(times, np.int64), np.array([item[1] for item in run]), np.array([item[2] for item in run])

        def after_step(k: int) -> None:
            t_state = est.state.t_ns
            if self._last_reported_t is None or t_state > self._last_reported_t:
                self._last_reported_t = t_state
                if self.on_fused is not None:
                    self.on_fused(self._fused_pose(gyro[k]))

        def after_steps(ks: list[int], t_state: np.ndarray, states: np.ndarray, covs: np.ndarray) -> None:
            last = self._last_reported_t
            first = 0 if last is None else int(np.searchsorted(t_state, last, side="right"))
            if first == len(ks):
                return
            self._last_reported_t = int(t_state[-1])
            if self.on_fused_run is None and self.on_fused is None:
                return
            run = self._fused_run(t_state[first:], states[first:], covs[first:], gyro, ks[first:])
            if self.on_fused_run is not None:
                self.on_fused_run(run)
            else:
                for pose in run.poses():
                    self.on_fused(pose)

        if est.process_imu_run(t_arr, gyro, accel, after_step, after_steps):  # it checks finiteness itself
            self._fused_until = times[-1]
            self._recent.clear()
            self._recent.append((times[-1], run[-1][1], run[-1][2]))
            return
        queue.extendleft(reversed(run))  # declined: the same samples, one at a time
        while run:
            run.pop()
            self._fuse_one_imu()

    def _batch_rows(self, first: int, last: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The times, gyro and accel of the ``n`` queued samples from ``first`` to ``last`` as slices of the batch
        they were added in; None if they were not added together (the batches that ended before are forgotten)."""
        self._forget_batches_before(first)
        if not self._batches:
            return None
        t, gyro, accel = self._batches[0]
        start = bisect_left(t, first)
        stop = start + n
        if stop > len(t) or t[start] != first or t[stop - 1] != last:
            return None
        return t[start:stop], gyro[start:stop], accel[start:stop]

    def _forget_batches_before(self, t_ns: int) -> None:
        """Forget the batches whose samples all came before ``t_ns``."""
        batches = self._batches
        while batches and batches[0][0][-1] < t_ns:
            batches.popleft()

    # ------------------------------------------------------------------------ prediction
    def _signature(self) -> tuple:
        """Changes whenever the filter state changed by more than propagation."""
        est = self.est
        others = sum(c.received for name, c in est.counts.items() if name != "imu")
        return (id(est.state), est.reset_counter, len(est.events), est.heading_aligned, est.position_initialized,
                others, est.state.n_landmarks if est.state is not None else 0)

    def _prediction_current(self, pred: _Prediction) -> bool:
        return (not self._measured and pred.signature == self._signature()
                and self._newest_t - pred.anchor_t_ns < _RESYNC_NS)

    def _step(self, pred: _Prediction, t: int, gyro: np.ndarray, accel: np.ndarray) -> None:
        _step_prediction(pred, t, gyro, accel, *self._biases(), float(self.est.propagator.gravity[2]),
                         self.est.health.gap_needs_reset)

    def _biases(self) -> tuple:
        """The state's (b_g, b_a) as tuples of floats, made again only when the state replaced them."""
        s = self.est.state
        biases = self._bias_floats
        if biases[0] is not s.b_g or biases[1] is not s.b_a:
            biases = self._bias_floats = (s.b_g, s.b_a, tuple(s.b_g.tolist()), tuple(s.b_a.tolist()))
        return biases[2], biases[3]

    def _repredict(self) -> _Prediction | None:
        """Propagate the delayed state through every buffered sample newer than it."""
        s = self.est.state
        if s is None:
            return None
        samples = list(chain(self._recent, ((t, g, a) for t, g, a, ok in self._queue if ok)))
        # The readings at the state's time: the last sample at or before it, interpolated towards the next one
        # when the state lies between them (a measurement's time), as the filter does (Estimator.imu_ahead).
        gyro, accel = np.zeros(3), np.zeros(3)
        if samples:
            i = max(bisect_right([x[0] for x in samples], s.t_ns) - 1, 0)
            t0, gyro, accel = samples[i]
            if t0 < s.t_ns and i + 1 < len(samples) and (samples[i + 1][0] - t0) * 1e-9 <= self.est.options.max_imu_gap_s:
                gyro, accel = reading_between(s.t_ns, samples[i], samples[i + 1])
        pred = _Prediction(s.t_ns, tuple(s.p.tolist()), tuple(s.v.tolist()), tuple(s.q.tolist()), gyro, accel,
                           self._newest_t or s.t_ns, self._signature())
        for t, g, a in samples:
            if t > s.t_ns:
                self._step(pred, t, g, a)
        self._measured = False
        return pred

    def output(self) -> OutputPose | None:
        """The pose at the newest IMU sample (None before the filter has started).

        Its covariance is the one :meth:`advance` prepared for the prediction (computed after the
        previous pose left, so at most one sample's growth behind), or computed here if none is.
        """
        if self.est.state is None:
            return None
        pred = self._fresh_prediction()
        cov9, pose_cov, omega_var = self._out_cov or self._predicted_covariance()
        s = self.est.state
        return OutputPose(  # in field order (positional: keyword handling is a quarter of a small call's cost)
            pred.t_ns, np.array(pred.p), np.array(pred.v), np.array(pred.q), pred.gyro - s.b_g, cov9, pose_cov,
            omega_var, *self._pose_flags(),
        )

    def _fresh_prediction(self) -> _Prediction:
        pred = self._pred
        if pred is None or self._measured or pred.signature != self._signature():
            pred = self._pred = self._repredict()
            self._out_cov = None
        return pred

    def _pose_flags(self) -> tuple:
        est = self.est
        t = est.state.t_ns
        return (est.heading_aligned, est.position_initialized, est.reset_counter, t, est.health.quality_cap(t),
                est.local_position)

    def detached(self) -> DetachedPrediction | None:
        """The prediction as it stands, able to go on without the filter (:class:`DetachedPrediction`): for a
        runtime that lets the filter work on another thread meanwhile. None before the filter has started or
        without a prediction to keep."""
        if self.est.state is None or not self.predict:
            return None
        pred = self._fresh_prediction()
        covariance = self._out_cov or self._predicted_covariance()
        s = self.est.state
        return DetachedPrediction(replace(pred), s.b_g, self._biases(),
                                  float(self.est.propagator.gravity[2]), self.est.health.gap_needs_reset,
                                  covariance, self._pose_flags())

    def heavy_due(self) -> bool:
        """Whether the next :meth:`advance` does milliseconds of work, not microseconds: it fuses a camera frame, or
        the periodic state check falls in it while the state holds a map (a factorisation of the whole covariance)."""
        if self._newest_t is None:
            return False
        horizon = self._newest_t - self.delay_ns
        pending = self._pending  # a heap: its first is the earliest, so mostly nothing to scan (every sample asks)
        if pending and pending[0][0] <= horizon and any(kind == "camera" and t <= horizon for t, _, _, kind, _ in pending):
            return True
        state = self.est.state
        return (state is not None and state.n_landmarks > 0 and bool(self._queue) and self._queue[0][0] <= horizon
                and self.est.health.check_would_be_due(horizon))

    def _predicted_covariance(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(cov9, pose_cov, omega_var) of the prediction: the delayed covariance grown to its time."""
        s, pred = self.est.state, self._pred
        cov9 = self.est.published_cov9()
        dt = (pred.t_ns - s.t_ns) * 1e-9
        if dt > 0.0:
            # Growth over the prediction: velocity error integrates into position, attitude error
            # mis-rotates the specific force, and the IMU's white noise adds its own share.
            f_w = (np.array(pred.v) - s.v) / dt - self.est.propagator.gravity
            a = skew(f_w)
            F = self._F
            F[0:3, 3:6] = self._eye3 * dt
            F[0:3, 6:9] = a * (-0.5 * dt * dt)
            F[3:6, 6:9] = a * -dt
            cov9 = F @ cov9 @ F.T + self._noise(np.array(pred.q), dt)
        return cov9, _pose_cov(cov9), self._omega_var()

    def _omega_var(self) -> np.ndarray:
        """Variance of the bias-corrected body rate: per-sample gyro noise plus the bias's."""
        s = self.est.state
        if s.layout.estimates_biases:
            return self._white_rate() + s.cov.diagonal()[BG]
        return self._white_rate().copy()

    def _white_rate(self) -> np.ndarray:
        """The gyro's white-noise rate variance (per axis), kept while the noise and rate stay."""
        est = self.est
        noise, rate = est.noise, est.calibration.imu.rate_hz
        white = self._white_rate_var
        if white is None or white[0] is not noise or white[1] != rate:
            white = self._white_rate_var = (noise, rate, noise.gyro_noise_density**2 * rate)
        return white[2]

    def _fused_run(self, t_ns: np.ndarray, states: np.ndarray, covs: np.ndarray, gyro: np.ndarray,
                   rows: list[int]) -> FusedRun:
        """:meth:`_fused_pose` of each of a run's steps that only propagated (end times, p, v, q rows, robot
        covariances, the run's gyro samples and each step's last among them), as arrays: nothing but the
        propagation has changed the state since the first of them."""
        est = self.est
        s = est.state
        return FusedRun(t_ns, states[:, 0:3], states[:, 3:6], states[:, 6:10], gyro, rows, s.b_g, covs,
                        self._white_rate(), s.layout.estimates_biases, est.heading_aligned, est.position_initialized,
                        est.reset_counter, est.health.quality_caps(t_ns.tolist()), est.local_position,
                        est.local_heading_floor())

    def _noise(self, q: np.ndarray, dt: float) -> np.ndarray:
        """IMU white noise over ``dt`` on [p, v, θ]; for isotropic noise, cached polynomials in dt."""
        noise = self.est.noise
        if self._q_terms is None or self._q_terms[0] is not noise:
            self._q_terms = (noise, noise_dt_polynomial(noise, _ROBOT9) if is_isotropic(noise) else None)
        terms = self._q_terms[1]
        if terms is None:
            return process_noise(q, dt, noise, _ROBOT9)
        c1, c2, c3 = terms
        return (c1 + (c2 + c3 * dt) * dt) * dt

    def _fused_pose(self, gyro: np.ndarray) -> OutputPose:
        """The filter's state as a pose (made after every step). Its nominal arrays are the state's own: the
        filter replaces them, never changes them in place (``FilterState``; a test holds every pose to
        what it was when made), so they need no copy."""
        est = self.est
        s = est.state
        cov9 = est.published_cov9()
        t = s.t_ns
        return OutputPose(  # in field order (positional: a quarter of this call's cost is keyword handling)
            t, s.p, s.v, s.q, gyro - s.b_g, cov9, _pose_cov(cov9), self._omega_var(), est.heading_aligned,
            est.position_initialized, est.reset_counter, t, est.health.quality_cap(t),
            est.local_position,
        )

    # --------------------------------------------------------------------------- status
    @property
    def next_pose_cov(self) -> np.ndarray | None:
        """The pose covariance :meth:`output` will hand out with the next pose while the prediction stays
        current (None if none is ready): outputs may write it now, after a pose left, not on the next one's path."""
        return self._out_cov[1] if self._out_cov is not None else None

    @property
    def newest_imu_t_ns(self) -> int | None:
        return self._newest_t

    @property
    def fused_until_ns(self) -> int | None:
        return self._fused_until

    @property
    def buffered_imu(self) -> int:
        return len(self._queue)

    @property
    def pending_measurements(self) -> int:
        return len(self._pending)

    def counts_report(self) -> dict:
        return {name: c.as_dict() for name, c in self.counts.items()}
