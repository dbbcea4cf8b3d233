"""IMU deltas: rotation and velocity increments accumulated over one filter step.

The filter does not need to step at the IMU's rate: like PX4's EKF2 it integrates the raw
samples into a delta angle and a delta velocity and propagates the covariance at a lower,
steady rate (≤ ``max_rate_hz``), which halves the cost at 200 Hz without losing the motion
between steps. Within a step each pair of consecutive samples is averaged (trapezoid) and the
specific force is rotated by the half-step attitude, so one-sample deltas reproduce exactly
what a per-sample filter would do.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vtolpose.estimator.core.rotation import quat_product, rotate, rotvec_quat
from vtolpose.estimator.inertial import sample_kernel


@dataclass(slots=True)
class ImuDelta:
    """Raw (bias-uncorrected) increments over ``[t0_ns, t1_ns]``, in the body frame at ``t0``.

    A value, never changed once made (not frozen: see :class:`~vtolpose.estimator.core.measurements.ImuSample`)."""

    t0_ns: int
    t1_ns: int
    dt: float
    dtheta: np.ndarray  # rotation vector of the accumulated body rotation
    dvel: np.ndarray  # ∫ ΔR(τ) f(τ) dτ, specific force rotated into the start frame [m/s]


@dataclass(slots=True)
class DeltaRun:
    """The steps a run of samples completed (:meth:`ImuDownsampler.add_run`), as arrays: row ``j`` is the
    step that sample ``ends[j]`` of the run ended."""

    ends: list[int]
    times: np.ndarray  # (m, 2): t0, t1 [ns]
    dts: np.ndarray  # (m,) [s]
    deltas: np.ndarray  # (m, 6): Δθ, Δv

    def delta(self, j: int) -> ImuDelta:
        return delta_row(self.times, self.dts, self.deltas, j)


def delta_row(times: np.ndarray, dts: np.ndarray, deltas: np.ndarray, j: int) -> ImuDelta:
    """Row ``j`` of steps given as arrays (rows of (t0, t1), dt, [Δθ, Δv]) as an :class:`ImuDelta`."""
    return ImuDelta(int(times[j, 0]), int(times[j, 1]), float(dts[j]), deltas[j, 0:3], deltas[j, 3:6])


_NO_READING = np.zeros(6)  # to_time without a next sample


def _log(q: tuple) -> np.ndarray:
    w, x, y, z = q
    n = math.sqrt(x * x + y * y + z * z)
    k = 2.0 * math.atan2(n, w) / n if n > 1e-12 else 2.0
    return np.array([k * x, k * y, k * z])


class ImuDownsampler:
    """Turns IMU samples into deltas of at least ``0.9 / max_rate_hz`` seconds.

    Its state is kept in one of two forms: plain floats and tuples for the per-sample path (:meth:`add`,
    :meth:`flush`, :meth:`hold`), or the two arrays the compiled calls of runs carry in and out
    (:meth:`add_run`, :meth:`to_time`), so that a replay's runs and fixes pass them from call to call as
    they are; each path converts the other's form once when it takes over (the same numbers)."""

    def __init__(self, max_rate_hz: float) -> None:
        self.min_dt = 0.9 / max_rate_hz
        # The newest sample: time, readings, and the readings as plain floats (the per-sample path's).
        self._last: tuple[int, np.ndarray, np.ndarray, list[float], list[float]] | None = None
        # The compiled calls' form, while they have the state: [last gyro, last accel, q, dv, dt] and
        # [last t, t0, flags (bit 0: a last sample, bit 1: a step started)]; None while the floats have it.
        self._packed: tuple[np.ndarray, np.ndarray] | None = None
        self._reset()

    def _reset(self) -> None:
        self._t0: int | None = None
        self._q = (1.0, 0.0, 0.0, 0.0)  # accumulated rotation since the step's start
        self._dv = (0.0, 0.0, 0.0)
        self._dt = 0.0

    def _pack(self) -> tuple[np.ndarray, np.ndarray]:
        """The state in the compiled calls' form (made from the floats if they have it)."""
        if self._packed is None:
            last, t0 = self._last, self._t0
            g, a = (last[3], last[4]) if last else ((0.0,) * 3, (0.0,) * 3)
            self._packed = (np.array([*g, *a, *self._q, *self._dv, self._dt]),
                            np.array([last[0] if last else 0, 0 if t0 is None else t0,
                                      (last is not None) | (t0 is not None) << 1], np.int64))
        return self._packed

    def _unpack(self) -> None:
        """The state back in floats, for the per-sample path (the last readings as arrays of the same values)."""
        if self._packed is None:
            return
        acc, acc_t = self._packed
        values = acc.tolist()
        t_last, t0, flags = acc_t.tolist()
        self._last = (t_last, acc[0:3].copy(), acc[3:6].copy(), values[0:3], values[3:6]) if flags & 1 else None
        self._t0 = t0 if flags & 2 else None
        self._q, self._dv, self._dt = tuple(values[6:10]), tuple(values[10:13]), values[13]
        self._packed = None

    def add(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray) -> ImuDelta | None:
        """Add a sample (strictly later than the previous); return a delta when one is complete.

        The live path, one sample at a time, kept in Python rather than calling the compiled
        ``sample_kernel.downsample_run`` on runs of one: a live service does not load the kernels of runs
        (~5 MB, tests/test_layout.py), and a compiled call per sample costs more than this. Its rotations
        are ``rotation``'s primitives, the ones the kernel calls; tests/test_imu_delta.py holds the two to
        the same bits."""
        if self._packed is not None:  # (per sample: no call when the floats have the state, as live)
            self._unpack()
        last = self._last
        # Scalar arithmetic on plain floats: this runs for every IMU sample.
        g, a = gyro.tolist(), accel.tolist()
        self._last = (t_ns, gyro, accel, g, a)
        if last is None:
            return None
        t_prev, _, _, (g0x, g0y, g0z), (a0x, a0y, a0z) = last
        if self._t0 is None:
            self._t0 = t_prev
        dt = (t_ns - t_prev) * 1e-9
        h = 0.5 * dt
        wx, wy, wz = h * (g0x + g[0]), h * (g0y + g[1]), h * (g0z + g[2])  # rotation vector of this sample step
        fx, fy, fz = h * (a0x + a[0]), h * (a0y + a[1]), h * (a0z + a[2])
        half = quat_product(*self._q, *rotvec_quat(0.5 * wx, 0.5 * wy, 0.5 * wz))
        dx, dy, dz = rotate(*half, fx, fy, fz)
        vx, vy, vz = self._dv
        self._dv = (vx + dx, vy + dy, vz + dz)
        self._q = quat_product(*self._q, *rotvec_quat(wx, wy, wz))
        self._dt += dt
        if self._dt < self.min_dt:
            return None
        return self.flush()

    def add_run(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> DeltaRun:
        """:meth:`add` for each row of a run of samples (strictly later, in time order), in one compiled
        call (``sample_kernel.downsample_run``): the completed deltas, each with its last sample's index."""
        acc, acc_t = self._pack()
        ends, times, dts, deltas = sample_kernel.downsample_run(t_ns, gyro, accel, acc, acc_t, self.min_dt)
        return DeltaRun(ends.tolist(), times, dts, deltas)

    def to_time(self, t_ns: int, after: tuple[int, np.ndarray, np.ndarray] | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`flush` then :meth:`hold` (``t_ns``, ``after``) in one compiled call (``sample_kernel.to_time``),
        for a process that fuses runs of samples (its kernels loaded): the deltas made, none, one or two, as
        rows of (t0, t1), dt and [Δθ, Δv]; the same numbers and the same state after as the two calls."""
        acc, acc_t = self._pack()
        reading = _NO_READING if after is None else np.concatenate((after[1], after[2]))
        return sample_kernel.to_time(acc, acc_t, t_ns, 0 if after is None else after[0], reading, after is not None)

    def flush(self) -> ImuDelta | None:
        """The partial delta accumulated so far (e.g. up to a measurement's time), if any."""
        self._unpack()
        if self._t0 is None or self._dt <= 0.0:
            return None
        delta = ImuDelta(self._t0, self._last[0], self._dt, _log(self._q), np.array(self._dv))
        self._reset()
        return delta

    def hold(self, t_ns: int, after: tuple[int, np.ndarray, np.ndarray] | None = None) -> ImuDelta | None:
        """A delta from the last sample to ``t_ns``, for a measurement that falls between samples. Call
        :meth:`flush` first; the next delta then starts at ``t_ns`` from the reading this one ends with.

        ``after``, the next sample (time, gyro, accel), if known: the reading at ``t_ns`` is interpolated
        linearly between the two and the part-step is the trapezoid up to it, so that the part-step and the
        rest of the step, which starts from that reading, together make the full step's trapezoid (the
        integral of the linear reading). Without it the last reading is held, and each measurement costs
        the step ½·Δω·(t_ns − t_last) of rotation (a lag under angular acceleration)."""
        self._unpack()
        if self._last is None or t_ns <= self._last[0] or self._t0 is not None:
            return None
        t_last, gyro, accel, g, a = self._last
        dt = (t_ns - t_last) * 1e-9
        if after is not None and after[0] > t_ns:
            g_at, a_at = reading_between(t_ns, (t_last, gyro, accel), after)
            self._last = (t_ns, g_at, a_at, g_at.tolist(), a_at.tolist())
            w, f = (0.5 * dt) * (gyro + g_at), (0.5 * dt) * (accel + a_at)
            half = rotvec_quat(*(0.5 * w).tolist())
            return ImuDelta(t_last, t_ns, dt, w, np.array(rotate(*half, *f.tolist())))
        self._last = (t_ns, gyro, accel, g, a)
        half = rotvec_quat(*(0.5 * dt * gyro).tolist())
        return ImuDelta(t_last, t_ns, dt, gyro * dt, np.array(rotate(*half, *(dt * accel).tolist())))


def reading_between(t_ns: int, before: tuple[int, np.ndarray, np.ndarray],
                    after: tuple[int, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The IMU reading (gyro, accel) at ``t_ns`` between two samples ``(time, gyro, accel)``, linearly: what
    the filter steps from at a measurement's time (:meth:`ImuDownsampler.hold`) and the output predictor
    starts from at the state's (``FusionCore``), so both agree."""
    t0, gyro, accel = before
    s = (t_ns - t0) / (after[0] - t0)
    return gyro + s * (after[1] - gyro), accel + s * (after[2] - accel)
