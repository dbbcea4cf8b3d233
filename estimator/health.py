"""Filter health: which sensors are alive, whether the filter is still sound, when it must reset.

The estimator (``vtolpose.estimator.filter``) asks short questions at the points where it can act:

- A sensor goes quiet or every measurement of it is refused: after ``gps_stale_s`` /
  ``camera_stale_s`` without a *used* measurement it is reported stale and the published
  quality is capped. Nothing is reset: the covariance grows on its own, honestly.
- A sensor's innovations stay beyond its gate (every GPS fix rejected for
  ``gps_reset_after_s``): the estimate, not the sensor, is wrong — the filter re-initialises
  position and velocity from that sensor, and its attitude too when it is lost again right
  after (:meth:`HealthMonitor.measured` says when).
- Innovations out of their band say the filter is lost, without any truth
  (:meth:`HealthMonitor.innovations`): for the camera, a frame whose landmarks in view are not
  found where predicted (few re-observed), whose matches' NIS is beyond its χ² band, or a
  map that keeps initialising landmarks it never sees again (churn); for the GPS, fixes the
  gate refuses. Out of band for ``innovation_cap_s`` caps the quality at
  ``innovation_quality_cap``; for ``innovation_reset_s`` the filter resets, attitude included,
  and says why (:func:`camera_verdict`).
- The filter itself breaks: a nominal state or covariance that is not finite, or a covariance
  that is not positive definite (:func:`state_problem`, every ``check_period_s``). The filter
  goes back to the last nominal state that passed the check, re-initialises its covariance
  from the sensors still alive and clears the map.
- The IMU stream has a hole longer than ``imu_gap_reset_s``: samples were lost, or every
  stamp stepped (a clock step) — the IMU alone cannot tell which. Rather than one giant
  propagation step, the filter restarts at the new sample with the nominal state held and the
  covariance widened to cover both readings (:func:`widen_for_gap`); GPS and camera then pull
  it back. Shorter gaps are propagated over, widened only by the unmodelled acceleration.

Every reset is counted (the ODOMETRY ``reset_counter``) and, for ``reset_hold_s`` after it,
caps the published quality. Pure computation: no I/O, no clocks.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from vtolpose.estimator.core.kalman import chi2_gate
from vtolpose.estimator.core.state import FilterState

RESET_KINDS = ("gps_rejected", "imu_gap", "state_invalid", "camera_lost")


@dataclass(frozen=True, slots=True)
class HealthOptions:
    imu_gap_reset_s: float = 1.0  # longer IMU gaps (or forward clock steps) are not propagated over
    gap_accel_sigma: float = 2.0  # m/s²: acceleration the vehicle may have had in a gap beyond the held sample
    gap_rate_sigma_deg: float = 3.0  # deg/s: turn rate it may have had beyond the held sample
    check_period_s: float = 1.0  # full covariance check (finite, positive definite) this often
    gps_stale_s: float = 1.0  # no fix used for this long: GPS stale
    camera_stale_s: float = 1.0  # no frame used for this long: camera stale
    stale_quality_cap: int = 50  # quality ceiling while a sensor that was in use is stale
    reset_quality_cap: int = 20  # quality ceiling for reset_hold_s after a reset
    reset_hold_s: float = 5.0
    innovation_cap_s: float = 1.0  # innovations out of band this long: quality capped ...
    innovation_quality_cap: int = 50  # ... at this
    innovation_reset_s: float = 3.0  # and this long: the filter is lost, reset
    camera_nis_probability: float = 0.999  # a frame's NIS beyond this χ² quantile is out of band
    min_in_view: int = 8  # landmarks predicted in view for a frame to be judged at all
    min_reobserved: float = 0.2  # fraction of them matched below this: out of band
    max_churn: float = 2.0  # landmarks initialised per match over the last second above this: out of band
    min_churn_landmarks: int = 10  # (once at least this many were initialised in it)

    def __post_init__(self) -> None:
        for name in ("imu_gap_reset_s", "check_period_s", "gps_stale_s", "camera_stale_s"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"health {name} must be positive, got {getattr(self, name)}")
        if not (self.gap_accel_sigma >= 0.0 and self.gap_rate_sigma_deg >= 0.0 and self.reset_hold_s >= 0.0):
            raise ValueError("health gap sigmas and reset_hold_s must be >= 0")
        if not (0 <= self.reset_quality_cap <= 100 and 0 <= self.stale_quality_cap <= 100
                and 0 <= self.innovation_quality_cap <= 100):
            raise ValueError("health quality caps must be within 0..100")
        if not (0.0 < self.innovation_cap_s <= self.innovation_reset_s):
            raise ValueError("health innovation_cap_s must be positive and at most innovation_reset_s")
        if not (0.0 < self.camera_nis_probability < 1.0 and 0.0 <= self.min_reobserved <= 1.0):
            raise ValueError("health camera_nis_probability must be in (0, 1) and min_reobserved in [0, 1]")


@dataclass(slots=True)
class SensorHealth:
    """Filter-time bookkeeping of one measurement stream."""

    last_t_ns: int | None = None  # last measurement that reached the filter
    last_used_t_ns: int | None = None  # last one it fused
    rejected_since_ns: int | None = None  # start of the current run of gate rejections
    used: int = 0


@dataclass(slots=True)
class InnovationRun:
    """A sensor's current run of out-of-band innovations (filter time)."""

    since_ns: int | None = None
    why: str = ""
    capped: int = 0  # runs that lasted long enough to cap the quality
    counted: bool = False  # the current run is among them


@dataclass(frozen=True, slots=True)
class FrameInnovations:
    """What one camera frame says about the filter: landmarks predicted in view, matched, new, and the NIS."""

    t_ns: int
    in_view: int
    matched: int
    initialised: int
    nis: float  # of the frame's update, NaN if none
    dof: int


def camera_verdict(frame: FrameInnovations, recent: deque[FrameInnovations], options: HealthOptions) -> tuple[bool | None, str]:
    """Whether a frame's innovations are in band (None: too little in view to say), and why not.

    ``recent`` holds the frames of the last second, this one included (for the churn).
    """
    initialised = sum(f.initialised for f in recent)
    matched = sum(f.matched for f in recent)
    if initialised >= options.min_churn_landmarks and initialised > options.max_churn * max(matched, 1):
        return False, f"{initialised} landmarks initialised in the last second for {matched} matches (churn)"
    if frame.in_view < options.min_in_view:
        return None, ""
    if frame.matched < options.min_reobserved * frame.in_view:
        return False, f"{frame.matched} of {frame.in_view} landmarks in view re-observed"
    if frame.dof and math.isfinite(frame.nis) and frame.nis > chi2_gate(frame.dof, options.camera_nis_probability):
        return False, f"frame NIS {frame.nis:.1f} beyond its {100 * options.camera_nis_probability:g} % band ({frame.dof} dof)"
    return True, ""


@dataclass(frozen=True, slots=True)
class Reset:
    t_ns: int
    kind: str  # one of RESET_KINDS
    reason: str


@dataclass(frozen=True, slots=True)
class Snapshot:
    """A nominal state that passed the health check (what a broken filter goes back to)."""

    t_ns: int
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    b_g: np.ndarray
    b_a: np.ndarray


def state_problem(state: FilterState) -> str | None:
    """Why ``state`` cannot be trusted, or None. Positive definiteness is tested on the correlation
    matrix (scale-free: a landmark metres away and a bias of 1e-4 weigh alike) with a tiny jitter."""
    parts = ("p", "v", "q", "b_g", "b_a", "landmarks")
    cov = state.cov
    # One pass over everything first (a check per part costs several times more); which part, only if one fails.
    if not np.isfinite(np.concatenate([getattr(state, name).ravel() for name in parts] + [cov.ravel()])).all():
        for name in parts:
            if not np.all(np.isfinite(getattr(state, name))):
                return f"nominal {name} not finite"
        return "covariance not finite"
    d = np.diagonal(cov)
    if not d.min() > 0.0:
        return f"covariance has a non-positive variance (index {int(np.argmin(d))})"
    s = 1.0 / np.sqrt(d)
    corr = (cov + cov.T) * 0.5 * s[:, None] * s[None, :]
    corr.flat[:: len(d) + 1] += 1e-9  # the diagonal
    try:
        np.linalg.cholesky(corr)
    except np.linalg.LinAlgError:
        return "covariance not positive definite"
    return None


def gap_variances(gap_s: float, speed: float, rate: float, options: HealthOptions, extrapolated: bool) -> np.ndarray:
    """Variances added to [δp, δv, δθ] (per axis) by an IMU gap that has lasted ``gap_s``.

    Extrapolated over (a short gap: the last sample is held): its error, an unmodelled
    acceleration ``a`` and turn rate ``w``: velocity ``a·dt``, position ``½a·dt²``, attitude
    ``w·dt``. Held (a long gap or a clock step: the nominal state stops): also the motion the
    held state leaves out, the distance flown ``|v|·dt`` and the turn ``|ω|·dt`` — because the
    gap may have been real time or no time at all.
    """
    dt = float(gap_s)
    a, w = options.gap_accel_sigma, math.radians(options.gap_rate_sigma_deg)
    var_p, var_v, var_th = (0.5 * a * dt * dt) ** 2, (a * dt) ** 2, (w * dt) ** 2
    if not extrapolated:
        var_p += (speed * dt) ** 2
        var_th += (rate * dt) ** 2
    return np.array([var_p, var_v, var_th])


class GapWidener:
    """The current hole in the IMU stream, widened as time passes without a sample.

    The filter calls :meth:`widen` whenever time moves on without IMU (a measurement's time, or
    the next sample's): the covariance grows by what the gap adds since the last call. Up to
    ``imu_gap_reset_s`` the last sample is extrapolated (measurements in the gap propagate the
    state holding it); beyond it the state is held instead (:attr:`holding`).
    """

    def __init__(self, options: HealthOptions, bridge_s: float) -> None:
        self.options = options
        self.bridge_s = bridge_s
        self.covered_s = 0.0  # the part of the current gap already in the covariance
        self.holding = False

    def widen(self, state: FilterState, gap_s: float, omega_b: np.ndarray) -> bool:
        """Account for a gap of ``gap_s`` so far. True when it has just passed the reset limit."""
        if gap_s <= self.bridge_s or gap_s <= self.covered_s:
            return False
        crossed = not self.holding and gap_s > self.options.imu_gap_reset_s
        self.holding = self.holding or crossed
        self._add(state, gap_s, omega_b)
        return crossed

    def lost(self, state: FilterState, lost_s: float, omega_b: np.ndarray) -> bool:
        """``lost_s`` of data vanished without time passing (a backward clock step). True: beyond the limit."""
        self.holding, self.covered_s = True, 0.0
        self._add(state, lost_s, omega_b)
        self.end()
        return lost_s > self.options.imu_gap_reset_s

    def end(self) -> None:
        """A sample arrived: the gap is over."""
        self.covered_s, self.holding = 0.0, False

    def _add(self, state: FilterState, gap_s: float, omega_b: np.ndarray) -> None:
        speed, rate = math.sqrt(float(state.v @ state.v)), math.sqrt(float(omega_b @ omega_b))
        extrapolated = not self.holding
        added = gap_variances(gap_s, speed, rate, self.options, extrapolated)
        added -= gap_variances(self.covered_s, speed, rate, self.options, extrapolated)
        idx = np.arange(9)
        state.cov[idx, idx] += np.repeat(np.maximum(added, 0.0), 3)
        self.covered_s = gap_s


class HealthMonitor:
    """Sensor ages, gate-failure runs, periodic state checks, resets; see the module docstring."""

    def __init__(self, options: HealthOptions, gps_reset_after_s: float, history: int = 16) -> None:
        self.options = options
        self.reject_limit_ns = {"gps": int(round(gps_reset_after_s * 1e9))}
        self.stale_ns = {"gps": int(round(options.gps_stale_s * 1e9)), "camera": int(round(options.camera_stale_s * 1e9))}
        self.sensors: dict[str, SensorHealth] = {}
        self.resets: deque[Reset] = deque(maxlen=history)  # the most recent, for the status
        self.reset_counts: dict[str, int] = {}
        self.snapshot: Snapshot | None = None
        self._next_check_ns: int | None = None
        self._hold_ns = int(round(options.reset_hold_s * 1e9))
        self._period_ns = int(round(options.check_period_s * 1e9))
        self.runs: dict[str, InnovationRun] = {}
        self.frames: deque[FrameInnovations] = deque(maxlen=64)  # the camera's last second of frames
        self._cap_ns = int(round(options.innovation_cap_s * 1e9))
        self._lost_ns = int(round(options.innovation_reset_s * 1e9))
        self.imu_missing_since_ns: int | None = None  # the last IMU sample before a hole the state is held over

    # ------------------------------------------------------------------------ measurements
    def measured(self, sensor: str, t_ns: int, used: bool, gated: bool = False) -> bool:
        """Record a measurement's fate. True: ``sensor``'s innovations have been beyond its gate
        for too long (``gated`` rejections only) — the caller re-initialises from it."""
        s = self.sensors.get(sensor)
        if s is None:
            s = self.sensors[sensor] = SensorHealth()
        s.last_t_ns = t_ns if s.last_t_ns is None else max(s.last_t_ns, t_ns)
        if used:
            s.last_used_t_ns, s.rejected_since_ns = t_ns, None
            s.used += 1
            return False
        limit = self.reject_limit_ns.get(sensor)
        if not gated or limit is None:
            return False
        if s.rejected_since_ns is None:
            s.rejected_since_ns = t_ns
            return False
        return t_ns - s.rejected_since_ns >= limit

    def innovations(self, sensor: str, t_ns: int, in_band: bool | None, why: str = "") -> bool:
        """Record whether ``sensor``'s latest innovations are in band (None: no verdict). True when they
        have been out of band for ``innovation_reset_s``: the filter is lost, the caller resets."""
        run = self.runs.get(sensor)
        if run is None:
            run = self.runs[sensor] = InnovationRun()
        if in_band is None:
            return False
        if in_band:
            run.since_ns, run.why = None, ""
            return False
        if run.since_ns is None:
            run.since_ns, run.counted = t_ns, False
        if not run.counted and t_ns - run.since_ns >= self._cap_ns:
            run.capped, run.counted = run.capped + 1, True
        run.why = why
        return t_ns - run.since_ns >= self._lost_ns

    def camera_frame(self, frame: FrameInnovations) -> tuple[bool, str]:
        """A camera frame's innovations: (lost, why) — lost when out of band for ``innovation_reset_s``."""
        self.frames.append(frame)
        while self.frames and frame.t_ns - self.frames[0].t_ns > 1_000_000_000:
            self.frames.popleft()
        verdict, why = camera_verdict(frame, self.frames, self.options)
        return self.innovations("camera", frame.t_ns, verdict, why), why

    def out_of_band(self, t_ns: int) -> list[tuple[str, float, str]]:
        """Sensors whose innovations are out of band at ``t_ns``: (name, for how long [s], why)."""
        return [(name, (t_ns - r.since_ns) * 1e-9, r.why) for name, r in sorted(self.runs.items())
                if r.since_ns is not None and t_ns >= r.since_ns]

    def imu_missing(self, last_sample_ns: int | None) -> None:
        """The IMU has been silent past ``imu_gap_reset_s`` since ``last_sample_ns`` (None: it is back). Meanwhile
        the state is held, not flown: the pose it gives is not one to navigate by (quality cap 0)."""
        self.imu_missing_since_ns = last_sample_ns

    def gap_needs_reset(self, gap_s: float) -> bool:
        return gap_s > self.options.imu_gap_reset_s

    # --------------------------------------------------------------------------- checks
    def check_would_be_due(self, t_ns: int) -> bool:
        """Whether :meth:`check_due` would say yes at ``t_ns`` (without taking the check)."""
        return self._next_check_ns is None or t_ns >= self._next_check_ns

    def check_due(self, t_ns: int) -> bool:
        if self._next_check_ns is None or t_ns >= self._next_check_ns:
            self._next_check_ns = t_ns + self._period_ns
            return True
        return False

    def check(self, state: FilterState) -> str | None:
        """The state's problem, or None — then it becomes the snapshot to fall back on."""
        problem = state_problem(state)
        if problem is None:
            self.snapshot = Snapshot(state.t_ns, state.p.copy(), state.v.copy(), state.q.copy(),
                                     state.b_g.copy(), state.b_a.copy())
        return problem

    # --------------------------------------------------------------------------- resets
    def record_reset(self, t_ns: int, kind: str, reason: str) -> None:
        self.resets.append(Reset(t_ns, kind, reason))
        self.reset_counts[kind] = self.reset_counts.get(kind, 0) + 1
        for s in self.sensors.values():
            s.rejected_since_ns = None
        for run in self.runs.values():
            run.since_ns = None
        self.frames.clear()

    def fresh(self, sensor: str, t_ns: int) -> bool:
        """Whether ``sensor`` had a measurement used within its stale limit before ``t_ns``."""
        s = self.sensors.get(sensor)
        return s is not None and s.last_used_t_ns is not None and t_ns - s.last_used_t_ns <= self.stale_ns.get(sensor, 0)

    # --------------------------------------------------------------------------- report
    def stale(self, t_ns: int) -> list[str]:
        """Sensors that were in use and have had nothing used for longer than their limit."""
        return [name for name, s in self.sensors.items()
                if s.last_used_t_ns is not None and name in self.stale_ns and t_ns - s.last_used_t_ns > self.stale_ns[name]]

    def quality_caps(self, t_ns: list[int]) -> list[int]:
        """:meth:`quality_cap` at each of ``t_ns`` (increasing, a run's steps): worked out once where none of the
        times it compares with (a reset's hold, a sensor going stale, an innovation run capped) falls among them."""
        first, last = t_ns[0], t_ns[-1]
        if self._edge_between(first, last):
            return [self.quality_cap(t) for t in t_ns]
        return [self.quality_cap(first)] * len(t_ns)

    def _edge_between(self, first: int, last: int) -> bool:
        """Whether the cap may change after ``first`` up to ``last``: the cap differs from each edge on."""
        if self.resets and first < self.resets[-1].t_ns + self._hold_ns <= last:
            return True
        stale_ns = self.stale_ns
        for name, s in self.sensors.items():
            limit = stale_ns.get(name)
            if limit is not None and s.last_used_t_ns is not None and first < s.last_used_t_ns + limit + 1 <= last:
                return True
        cap_ns = self._cap_ns
        return any(run.since_ns is not None and first < run.since_ns + cap_ns <= last for run in self.runs.values())

    def quality_cap(self, t_ns: int) -> int:
        """Ceiling on the published quality: 100 when healthy (per-call cost: a few comparisons)."""
        cap = 100
        if self.imu_missing_since_ns is not None:
            return 0
        if self.resets and t_ns - self.resets[-1].t_ns < self._hold_ns:
            cap = self.options.reset_quality_cap
        for name, s in self.sensors.items():
            limit = self.stale_ns.get(name)
            if limit is not None and s.last_used_t_ns is not None and t_ns - s.last_used_t_ns > limit:
                cap = min(cap, self.options.stale_quality_cap)
        for run in self.runs.values():
            if run.since_ns is not None and t_ns - run.since_ns >= self._cap_ns:
                cap = min(cap, self.options.innovation_quality_cap)
        return cap

    def report(self, t_ns: int | None) -> dict:
        """For the status document: per-sensor ages in filter time, resets, degraded flags."""
        sensors = {}
        for name, s in sorted(self.sensors.items()):
            sensors[name] = {
                "age_s": None if t_ns is None or s.last_t_ns is None else round((t_ns - s.last_t_ns) * 1e-9, 3),
                "used_age_s": None if t_ns is None or s.last_used_t_ns is None else round((t_ns - s.last_used_t_ns) * 1e-9, 3),
                "used": s.used,
            }
        stale = self.stale(t_ns) if t_ns is not None else []
        for name in stale:
            sensors[name]["stale"] = True
        last = self.resets[-1] if self.resets else None
        degraded = [f"{name}_stale" for name in sorted(stale)]
        innovations = {}
        for name, seconds, why in (self.out_of_band(t_ns) if t_ns is not None else []):
            innovations[name] = {"out_of_band_s": round(seconds, 3), "why": why}
            if seconds >= self.options.innovation_cap_s:
                degraded.append(f"{name}_innovations")
        if last is not None and t_ns is not None and t_ns - last.t_ns < self._hold_ns:
            degraded.append(f"recent_reset_{last.kind}")
        if self.imu_missing_since_ns is not None:
            degraded.append("imu_missing")
            sensors["imu"] = {"stale": True, "used_age_s": None if t_ns is None
                              else round((t_ns - self.imu_missing_since_ns) * 1e-9, 3)}
        return {
            "sensors": sensors,
            "resets": dict(sorted(self.reset_counts.items())),
            "last_reset": None if last is None else {"t_ns": last.t_ns, "kind": last.kind, "reason": last.reason},
            "degraded": degraded,
            "innovations_out_of_band": innovations,
            "quality_cap": self.quality_cap(t_ns) if t_ns is not None else 0,
        }
