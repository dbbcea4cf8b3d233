"""Still periods: zero velocity and the gyro bias, measured whenever the vehicle rests.

On the pad, on a table, or landed, the IMU says more than "no motion": its mean rate *is*
the gyro bias. The thesis calibrates before each run (section 5.2); doing it at every rest
keeps a fixed-bias model (``thesis``) honest over long runs and gives the ``biases`` model a
direct bias measurement. A still chunk needs low IMU variance, a specific force of magnitude g,
and a filter speed near zero, so a smooth, straight flight is never mistaken for rest. The
variance is that of means over ``average_s`` (see ``initializer``): a turning rotor shakes
the IMU without moving the vehicle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vtolpose.estimator.inertial import sample_kernel


@dataclass(slots=True)
class StillnessOptions:
    enabled: bool = True
    chunk_s: float = 1.0
    gyro_std_max: float = 0.02  # rad/s per axis
    accel_std_max: float = 0.15  # m/s² per axis
    average_s: float = 0.1  # the std limits apply to means over this long (vibration averages out, motion not)
    gravity_tolerance: float = 0.3  # m/s² on |mean f| - g
    speed_max: float = 0.2  # m/s, filter estimate
    zupt_sigma: float = 0.01  # m/s


@dataclass(frozen=True, slots=True)
class StillChunk:
    """Statistics of one still chunk of IMU samples."""

    gyro_mean: np.ndarray
    gyro_var_of_mean: np.ndarray  # per axis, from the scatter of the chunk's block means
    n: int
    duration_s: float


class StillnessDetector:
    """Accumulates IMU samples in fixed chunks and reports each chunk that was still.

    A chunk counts as still when its scatter is low, |f| is g, the filter is not moving, and
    its means agree with those of the chunk before (which must have been quiet too).
    """

    def __init__(self, options: StillnessOptions) -> None:
        self.options = options
        self._previous: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        # After a run, the accumulation as the compiled kernel keeps it (sums, counts): the next run takes it as
        # it is, and anything else unpacks it into the fields first (_unpack).
        self._packed: tuple[np.ndarray, np.ndarray] | None = None
        self._reset(None)

    def _reset(self, t_ns: int | None) -> None:
        self._packed = None
        self._t0 = t_ns
        self._samples = 0
        self._n = 0  # block means in this chunk
        self._g_sum = np.zeros(3)
        self._g_sq = np.zeros(3)
        self._a_sum = np.zeros(3)
        self._a_sq = np.zeros(3)
        self._start_block(t_ns)

    def _start_block(self, t_ns: int | None) -> None:
        self._block_t0 = t_ns
        self._block_n = 0
        self._block_g = (0.0, 0.0, 0.0)  # plain floats: added to for every sample
        self._block_a = (0.0, 0.0, 0.0)

    def add(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray, gravity: float, speed: float) -> StillChunk | None:
        """Add a body-frame sample; at the end of each chunk return it if it was still.

        The live path, one sample at a time: the compiled accumulation (:meth:`add_run`) is a kernel of runs,
        which a live service does not load (tests/test_layout.py); tests/test_stillness.py holds the two to the
        same bits."""
        if self._packed is not None:
            self._unpack()
        if self._t0 is None:
            self._reset(t_ns)
        self._samples += 1
        self._block_n += 1
        (sgx, sgy, sgz), (sax, say, saz) = self._block_g, self._block_a
        gx, gy, gz = gyro.tolist()
        ax, ay, az = accel.tolist()
        self._block_g = (sgx + gx, sgy + gy, sgz + gz)
        self._block_a = (sax + ax, say + ay, saz + az)
        if (t_ns - self._block_t0) * 1e-9 >= self.options.average_s:
            g, a = np.array(self._block_g) / self._block_n, np.array(self._block_a) / self._block_n
            self._n += 1
            self._g_sum += g
            self._g_sq += g * g
            self._a_sum += a
            self._a_sq += a * a
            self._start_block(t_ns)
        duration = (t_ns - self._t0) * 1e-9
        if duration < self.options.chunk_s:
            return None
        chunk = self._evaluate(duration, gravity, speed)
        self._reset(t_ns)
        return chunk

    def add_run(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> list[tuple[int, float, np.ndarray]]:
        """:meth:`add`'s accumulation for each row of a run, in one compiled call (``sample_kernel``): the
        chunks that ended, as (index of their last sample, duration, statistics) for :meth:`judge`, which
        the caller calls for each in turn with the filter's speed at that sample."""
        if self._packed is None:
            sums, counts = np.zeros(18), np.zeros(6, np.int64)
            if self._t0 is not None:
                sums[0:3], sums[3:6], sums[6:9], sums[9:12] = self._g_sum, self._g_sq, self._a_sum, self._a_sq
                sums[12:15], sums[15:18] = self._block_g, self._block_a
                counts[:] = (self._t0, self._block_t0, self._samples, self._n, self._block_n, 1)
        else:
            sums, counts = self._packed
        ends, durations, stats = sample_kernel.stillness_run(t_ns, gyro, accel, sums, counts, self.options.average_s,
                                                             self.options.chunk_s)
        if counts[5]:
            self._packed = sums, counts
        if not len(ends):
            return []
        return list(zip(ends.tolist(), durations.tolist(), stats))

    def _unpack(self) -> None:
        """The kernel's (sums, counts) back into the fields the per-sample path and the judgement use."""
        sums, counts = self._packed
        self._packed = None
        self._t0, self._block_t0, self._samples, self._n, self._block_n = (int(c) for c in counts[:5].tolist())
        self._g_sum, self._g_sq, self._a_sum, self._a_sq = sums[0:3], sums[3:6], sums[6:9], sums[9:12]
        values = sums[12:18].tolist()
        self._block_g, self._block_a = tuple(values[0:3]), tuple(values[3:6])

    def judge(self, duration: float, stats: np.ndarray, gravity: float, speed: float) -> StillChunk | None:
        """What :meth:`add` returns at a chunk's end, for a chunk :meth:`add_run` reported."""
        if self._packed is not None:
            self._unpack()
        current = (self._n, self._samples, self._g_sum, self._g_sq, self._a_sum, self._a_sq)
        self._g_sum, self._g_sq, self._a_sum, self._a_sq = stats[0:3], stats[3:6], stats[6:9], stats[9:12]
        self._samples, self._n = int(stats[12]), int(stats[13])
        try:
            return self._evaluate(duration, gravity, speed)
        finally:
            self._n, self._samples, self._g_sum, self._g_sq, self._a_sum, self._a_sq = current

    def _evaluate(self, duration: float, gravity: float, speed: float) -> StillChunk | None:
        opts = self.options
        n = self._n
        if n < 5 or self._samples < 10:
            return None
        g_mean = self._g_sum / n
        a_mean = self._a_sum / n
        g_var = np.maximum(self._g_sq / n - g_mean**2, 0.0)
        a_var = np.maximum(self._a_sq / n - a_mean**2, 0.0)
        quiet = (
            (g_var < opts.gyro_std_max**2).all()
            and (a_var < opts.accel_std_max**2).all()
            and abs(math.sqrt(float(a_mean @ a_mean)) - gravity) < opts.gravity_tolerance
            and speed < opts.speed_max
        )
        previous, self._previous = self._previous, (g_mean, g_var / n, a_mean, a_var / n) if quiet else None
        if not quiet or previous is None:
            return None
        # A slow, smooth motion (an arm starting to move, a gentle drift) keeps the scatter low
        # but shifts the mean: demand that this chunk's means agree with the previous chunk's.
        pg, pg_var, pa, pa_var = previous
        if ((g_mean - pg) ** 2 > 16.0 * (g_var / n + pg_var)).any() or ((a_mean - pa) ** 2 > 16.0 * (a_var / n + pa_var)).any():
            return None
        return StillChunk(g_mean, g_var / n, self._samples, duration)
