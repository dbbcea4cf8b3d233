"""Per-sample IMU bookkeeping over a run of samples, compiled to machine code.

Between two measurements a replay hands the filter dozens of IMU samples. What each sample does
that does not depend on the filter state, accumulating the delta angle and velocity of the next
step (``imu_delta.ImuDownsampler``) and the block and chunk sums of the rest detector
(``stillness.StillnessDetector``), runs here for the whole run in one call, with each sample's
operations in the same order as the per-sample code: the deltas and statistics are bit for bit
the same (tests hold them together). The estimator then acts on what came out (a step to
propagate, a chunk to judge with the filter's speed) in sample order.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vtolpose.estimator.core.rotation import compiled_quat_product as quat_product
from vtolpose.estimator.core.rotation import compiled_rotate as rotate
from vtolpose.estimator.core.rotation import compiled_rotvec_quat as rotvec_quat


@numba.njit(cache=True, nogil=True)
def downsample_run(t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, acc: np.ndarray, acc_t: np.ndarray,
                   min_dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:meth:`ImuDownsampler.add` for every sample of a run, the accumulator carried in and out.

    ``acc`` (float, 14): the previous sample's gyro (3) and accel (3), the rotation so far (4), Δv (3),
    the time so far; ``acc_t`` (int, 3): the previous sample's time, the step's start, and flags
    (bit 0: a previous sample, bit 1: a step started). Returns, per completed step, the index of the
    sample that ended it, (t0, t1), dt, and [Δθ, Δv] (6).
    """
    n = t.shape[0]
    ends = np.empty(n, np.int64)
    times = np.empty((n, 2), np.int64)
    dts = np.empty(n)
    deltas = np.empty((n, 6))
    m = 0
    for k in range(n):
        tk = t[k]
        gx, gy, gz = gyro[k, 0], gyro[k, 1], gyro[k, 2]
        ax, ay, az = accel[k, 0], accel[k, 1], accel[k, 2]
        had_last = acc_t[2] & 1
        t_prev = acc_t[0]
        g0x, g0y, g0z, a0x, a0y, a0z = acc[0], acc[1], acc[2], acc[3], acc[4], acc[5]
        acc[0], acc[1], acc[2], acc[3], acc[4], acc[5] = gx, gy, gz, ax, ay, az
        acc_t[0] = tk
        acc_t[2] |= 1
        if not had_last:
            continue
        if not acc_t[2] & 2:
            acc_t[1] = t_prev
            acc_t[2] |= 2
        dt = (tk - t_prev) * 1e-9
        h = 0.5 * dt
        wx, wy, wz = h * (g0x + gx), h * (g0y + gy), h * (g0z + gz)
        fx, fy, fz = h * (a0x + ax), h * (a0y + ay), h * (a0z + az)
        qw, qx, qy, qz = acc[6], acc[7], acc[8], acc[9]
        hw, hx, hy, hz = rotvec_quat(0.5 * wx, 0.5 * wy, 0.5 * wz)
        hw, hx, hy, hz = quat_product(qw, qx, qy, qz, hw, hx, hy, hz)
        ux, uy, uz = rotate(hw, hx, hy, hz, fx, fy, fz)  # the specific force at the half-step attitude
        acc[10] = acc[10] + ux
        acc[11] = acc[11] + uy
        acc[12] = acc[12] + uz
        dw, dx, dy, dz = rotvec_quat(wx, wy, wz)
        acc[6], acc[7], acc[8], acc[9] = quat_product(qw, qx, qy, qz, dw, dx, dy, dz)
        acc[13] += dt
        if acc[13] < min_dt or acc[13] <= 0.0:
            continue
        ends[m] = k
        _complete_step(acc, acc_t, tk, times, dts, deltas, m)
        m += 1
    return ends[:m], times[:m], dts[:m], deltas[:m]


@numba.njit(cache=True, nogil=True)
def _complete_step(acc: np.ndarray, acc_t: np.ndarray, t1: int, times: np.ndarray, dts: np.ndarray,
                   deltas: np.ndarray, m: int) -> None:
    """The accumulated step as row ``m`` (:meth:`ImuDownsampler.flush`): from the accumulator's start to ``t1``,
    its rotation vector and Δv; then a fresh start."""
    w, x, y, z = acc[6], acc[7], acc[8], acc[9]
    norm = math.sqrt(x * x + y * y + z * z)
    scale = 2.0 * math.atan2(norm, w) / norm if norm > 1e-12 else 2.0
    times[m, 0], times[m, 1] = acc_t[1], t1
    dts[m] = acc[13]
    deltas[m, 0], deltas[m, 1], deltas[m, 2] = scale * x, scale * y, scale * z
    deltas[m, 3], deltas[m, 4], deltas[m, 5] = acc[10], acc[11], acc[12]
    acc[6], acc[7], acc[8], acc[9] = 1.0, 0.0, 0.0, 0.0
    acc[10], acc[11], acc[12], acc[13] = 0.0, 0.0, 0.0, 0.0
    acc_t[2] &= ~2


@numba.njit(cache=True, nogil=True)
def to_time(acc: np.ndarray, acc_t: np.ndarray, t_ns: int, after_t: int, after: np.ndarray,
            has_after: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:meth:`ImuDownsampler.flush` then :meth:`ImuDownsampler.hold` to ``t_ns`` (``after``: the next sample's
    gyro and accel, at ``after_t``, if ``has_after``), the accumulator carried in and out as in
    :func:`downsample_run` (an interpolated reading at ``t_ns`` becomes its last sample's). Returns (t0, t1), dt
    and [Δθ, Δv] of the deltas made: none, one or two."""
    times = np.empty((2, 2), np.int64)
    dts = np.empty(2)
    deltas = np.empty((2, 6))
    m = 0
    if acc_t[2] & 2 and acc[13] > 0.0:  # flush: the partial step up to the last sample, then a fresh start
        _complete_step(acc, acc_t, acc_t[0], times, dts, deltas, 0)
        m = 1
    t_last = acc_t[0]
    if not acc_t[2] & 1 or t_ns <= t_last or acc_t[2] & 2:
        return times[:m], dts[:m], deltas[:m]
    dt = (t_ns - t_last) * 1e-9
    gx, gy, gz, ax, ay, az = acc[0], acc[1], acc[2], acc[3], acc[4], acc[5]
    times[m, 0], times[m, 1] = t_last, t_ns
    dts[m] = dt
    acc_t[0] = t_ns
    if has_after and after_t > t_ns:
        # reading_between: the reading at t_ns on the line to the next sample; the trapezoid up to it.
        s = (t_ns - t_last) / (after_t - t_last)
        bx, by, bz = gx + s * (after[0] - gx), gy + s * (after[1] - gy), gz + s * (after[2] - gz)
        cx, cy, cz = ax + s * (after[3] - ax), ay + s * (after[4] - ay), az + s * (after[5] - az)
        h = 0.5 * dt
        wx, wy, wz = h * (gx + bx), h * (gy + by), h * (gz + bz)
        fx, fy, fz = h * (ax + cx), h * (ay + cy), h * (az + cz)
        hw, hx, hy, hz = rotvec_quat(0.5 * wx, 0.5 * wy, 0.5 * wz)
        deltas[m, 0], deltas[m, 1], deltas[m, 2] = wx, wy, wz
        deltas[m, 3], deltas[m, 4], deltas[m, 5] = rotate(hw, hx, hy, hz, fx, fy, fz)
        acc[0], acc[1], acc[2], acc[3], acc[4], acc[5] = bx, by, bz, cx, cy, cz
        return times[:m + 1], dts[:m + 1], deltas[:m + 1]
    h = 0.5 * dt
    hw, hx, hy, hz = rotvec_quat(h * gx, h * gy, h * gz)
    deltas[m, 0], deltas[m, 1], deltas[m, 2] = gx * dt, gy * dt, gz * dt
    deltas[m, 3], deltas[m, 4], deltas[m, 5] = rotate(hw, hx, hy, hz, dt * ax, dt * ay, dt * az)
    return times[:m + 1], dts[:m + 1], deltas[:m + 1]


@numba.njit(cache=True, nogil=True)
def stillness_run(t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, sums: np.ndarray, counts: np.ndarray,
                  average_s: float, chunk_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:meth:`StillnessDetector.add`'s accumulation for every sample of a run, its state carried in and out.

    ``sums`` (float, 18): g_sum, g_sq, a_sum, a_sq (of block means), then the open block's gyro and
    accel sums; ``counts`` (int, 6): chunk start, block start, samples, block means, samples in the
    block, and 1 once a chunk is open. Returns, per chunk that ended, the index of its last sample,
    its duration, and its statistics before the reset ([g_sum, g_sq, a_sum, a_sq], samples, means).
    """
    n = t.shape[0]
    ends = np.empty(n, np.int64)
    stats = np.empty((n, 14))
    durations = np.empty(n)
    m = 0
    for k in range(n):
        tk = t[k]
        if counts[5] == 0:  # _reset(t): a chunk and a block start here
            counts[0], counts[1], counts[2], counts[3], counts[4], counts[5] = tk, tk, 0, 0, 0, 1
            sums[:] = 0.0
        counts[2] += 1
        counts[4] += 1
        sums[12], sums[13], sums[14] = sums[12] + gyro[k, 0], sums[13] + gyro[k, 1], sums[14] + gyro[k, 2]
        sums[15], sums[16], sums[17] = sums[15] + accel[k, 0], sums[16] + accel[k, 1], sums[17] + accel[k, 2]
        if (tk - counts[1]) * 1e-9 >= average_s:
            block_n = counts[4]
            counts[3] += 1
            for i in range(3):
                g = sums[12 + i] / block_n
                a = sums[15 + i] / block_n
                sums[i] += g
                sums[3 + i] += g * g
                sums[6 + i] += a
                sums[9 + i] += a * a
            counts[1], counts[4] = tk, 0
            sums[12:18] = 0.0
        duration = (tk - counts[0]) * 1e-9
        if duration < chunk_s:
            continue
        ends[m] = k
        durations[m] = duration
        stats[m, 0:12] = sums[0:12]
        stats[m, 12], stats[m, 13] = counts[2], counts[3]
        m += 1
        counts[0], counts[1], counts[2], counts[3], counts[4] = tk, tk, 0, 0, 0
        sums[:] = 0.0
    return ends[:m], durations[:m], stats[:m]


@numba.njit(cache=True, nogil=True)
def level_run(t: np.ndarray, accel: np.ndarray, sums: np.ndarray, state: np.ndarray,
              interval_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The levelling's accumulation (``Estimator._level``) for every sample of a run, carried in and out:
    ``sums`` (3) the specific force summed so far, ``state`` (int, 2) how many samples and since when.
    Returns, per interval that ended, the index of its last sample and its mean specific force."""
    n = t.shape[0]
    ends = np.empty(n, np.int64)
    means = np.empty((n, 3))
    m = 0
    for k in range(n):
        sums[0], sums[1], sums[2] = sums[0] + accel[k, 0], sums[1] + accel[k, 1], sums[2] + accel[k, 2]
        state[0] += 1
        if (t[k] - state[1]) * 1e-9 < interval_s:
            continue
        ends[m] = k
        means[m, 0], means[m, 1], means[m, 2] = sums[0] / state[0], sums[1] / state[0], sums[2] / state[0]
        m += 1
        sums[:] = 0.0
        state[0], state[1] = 0, t[k]
    return ends[:m], means[:m]


@numba.njit(cache=True, nogil=True)
def screen_rows(gyro: np.ndarray, accel: np.ndarray, gyro2_max: float, accel2_max: float) -> tuple[np.ndarray, np.ndarray]:
    """Per row: beyond the IMU's range (``ImuRange.exceeded``: a squared norm above ``gyro2_max`` or
    ``accel2_max``, both infinite for no range) and finite (``readings_finite``), with their arithmetic.
    Whole columns at a time: the same operations per row, and a few numpy calls when interpreted."""
    gx, gy, gz = gyro[:, 0], gyro[:, 1], gyro[:, 2]
    ax, ay, az = accel[:, 0], accel[:, 1], accel[:, 2]
    g2 = gx * gx + gy * gy + gz * gz
    a2 = ax * ax + ay * ay + az * az
    finite = np.isfinite(g2 + ax * ax + ay * ay + az * az)  # the one sum of six squares, left to right
    exceeded = ((g2 > gyro2_max) | (a2 > accel2_max)) & np.isfinite(g2 + a2)
    return exceeded, finite


@numba.njit(cache=True, nogil=True)
def plain_run(t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, last_t: int, max_gap_s: float) -> bool:
    """Every sample finite (``readings_finite``), each later than the one before (the first than ``last_t``)
    by no more than ``max_gap_s`` (compared as the estimator's gap check does): a run it takes whole."""
    n = t.shape[0]
    if n == 0:
        return True
    steps = np.empty(n, np.int64)
    steps[0] = t[0] - last_t
    steps[1:] = t[1:] - t[:-1]
    if np.any(steps <= 0) or np.any(steps * 1e-9 > max_gap_s):
        return False
    return bool(np.all(screen_rows(gyro, accel, np.inf, np.inf)[1]))


def warm_up(runs: bool = True) -> None:
    """Compile (or load from the cache) for the argument types the estimator passes. ``runs``: also the
    kernels of runs of samples, which only a process fusing runs (a replay) calls."""
    t = np.arange(4, dtype=np.int64) * 5_000_000
    rows = np.zeros((4, 3))
    screen_rows(rows, rows, 2700.0, 76800.0)
    if runs:
        downsample_run(t, rows, rows, np.zeros(14), np.zeros(3, np.int64), 0.009)
        to_time(np.zeros(14), np.array([1, 0, 1], np.int64), 3, 5, np.zeros(6), True)
        stillness_run(t, rows, rows, np.zeros(18), np.zeros(6, np.int64), 0.1, 1.0)
        level_run(t, rows, np.zeros(3), np.zeros(2, np.int64), 0.5)
        plain_run(t, rows, rows, -1, 0.1)
