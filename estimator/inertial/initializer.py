"""Initial attitude from the IMU: roll and pitch from gravity, gyro bias, gravity magnitude.

The thesis calibrates before each run from a static stretch (section 5.2). Here the filter
waits for a window in which the IMU is still; if none comes within ``max_wait_s`` (the vehicle
is already moving, as at the start of EuRoC MH01) it starts from the mean of the last window
with wider uncertainties instead of waiting forever.

"Still" means no motion, not no vibration: a helicopter on the pad with its rotor turning
shakes its IMU by ±0.5 m/s² at tens of hertz while it does not move at all. Stillness is
therefore judged on means over ``average_s`` (0.1 s: motion of a vehicle lies below 5 Hz,
vibration above), and the bias' uncertainty comes from the scatter of those means.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from vtolpose.estimator.core.rotation import quat_from_euler


@dataclass(slots=True)
class InitOptions:
    static_window_s: float = 2.0
    max_wait_s: float = 3.0
    gyro_std_max: float = 0.02  # rad/s, per axis, over the window
    accel_std_max: float = 0.15  # m/s^2, per axis, over the window
    average_s: float = 0.1  # the std limits apply to means over this long (vibration averages out, motion not)
    estimate_gravity: bool = True  # the service resolves the config's 'auto' per variant
    sigma_attitude_static_deg: float = 0.5
    sigma_attitude_moving_deg: float = 5.0
    sigma_heading_known_deg: float = 2.0
    sigma_velocity_static: float = 0.02
    sigma_velocity_moving: float = 1.0
    sigma_gyro_bias: float = 0.1  # rad/s, prior when no static window gives it (a MEMS gyro's turn-on bias)
    sigma_accel_bias: float = 0.1  # m/s^2


@dataclass(frozen=True, slots=True)
class InitialAttitude:
    t_ns: int
    q: np.ndarray
    gyro_bias: np.ndarray
    gravity: float
    static: bool
    sigma_roll_pitch: float  # rad
    sigma_gyro_bias: float  # rad/s
    n_samples: int


def roll_pitch_from_specific_force(f_b: np.ndarray) -> tuple[float, float]:
    """Roll and pitch of a body at rest: its accelerometer reads ``f_B = -R^T g_W``."""
    roll = math.atan2(-f_b[1], -f_b[2])
    pitch = math.atan2(f_b[0], math.hypot(f_b[1], f_b[2]))
    return roll, pitch


def block_means(t_ns: np.ndarray, values: np.ndarray, average_s: float) -> np.ndarray:
    """Means of ``values`` over consecutive blocks of ``average_s`` (a trailing partial block is dropped);
    the samples themselves when a block would hold fewer than two."""
    span = (t_ns[-1] - t_ns[0]) * 1e-9
    per_block = int(round(average_s * (len(t_ns) - 1) / span)) if span > 0.0 else 1
    if per_block < 2 or len(t_ns) < 4 * per_block:
        return values
    n = len(values) // per_block * per_block
    return values[:n].reshape(-1, per_block, values.shape[1]).mean(axis=1)


class StaticInitializer:
    """Feed IMU samples; returns an :class:`InitialAttitude` once it can."""

    def __init__(self, options: InitOptions, nominal_gravity: float, heading_rad: float = 0.0) -> None:
        self.options = options
        self.nominal_gravity = nominal_gravity
        self.heading_rad = heading_rad
        self._t: deque[int] = deque()
        self._gyro: deque[np.ndarray] = deque()
        self._accel: deque[np.ndarray] = deque()
        self._first_t: int | None = None

    def add(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray) -> InitialAttitude | None:
        """Returns the initial attitude once a still window exists, or once ``max_wait_s`` has passed
        without one (then from the last window, less certain)."""
        opts = self.options
        if self._first_t is None:
            self._first_t = t_ns
        self.keep(t_ns, gyro, accel)
        window_ns = int(opts.static_window_s * 1e9)
        full = self._t[-1] - self._t[0] >= 0.95 * window_ns and len(self._t) >= 10
        if not full:
            return None
        g = np.array(self._gyro)
        a = np.array(self._accel)
        g_means, a_means = block_means(np.array(self._t), g, opts.average_s), block_means(np.array(self._t), a, opts.average_s)
        static = bool(np.all(g_means.std(axis=0) < opts.gyro_std_max) and np.all(a_means.std(axis=0) < opts.accel_std_max))
        timed_out = t_ns - self._first_t >= int(opts.max_wait_s * 1e9)
        if not (static or timed_out):
            return None
        return self._solve(t_ns, g, a, g_means, static)

    def keep(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Only hold the sample in the window (no judgement): for :meth:`latest` later."""
        window_ns = int(self.options.static_window_s * 1e9)
        self._t.append(t_ns)
        self._gyro.append(gyro)
        self._accel.append(accel)
        while self._t[-1] - self._t[0] > window_ns:
            self._t.popleft()
            self._gyro.popleft()
            self._accel.popleft()

    def latest(self) -> InitialAttitude | None:
        """A moving start from the window as it is now (None while it holds fewer than ten samples)."""
        if len(self._t) < 10:
            return None
        g = np.array(self._gyro)
        return self._solve(self._t[-1], g, np.array(self._accel), block_means(np.array(self._t), g, self.options.average_s),
                           False)

    def as_moving(self, init: InitialAttitude) -> InitialAttitude:
        """``init`` judged again as a moving start (the GPS says the "still" window was steady motion)."""
        g, a = np.array(self._gyro), np.array(self._accel)
        return self._solve(init.t_ns, g, a, block_means(np.array(self._t), g, self.options.average_s), False)

    def _solve(self, t_ns: int, g: np.ndarray, a: np.ndarray, g_means: np.ndarray, static: bool) -> InitialAttitude:
        opts = self.options
        f_mean = a.mean(axis=0)
        roll, pitch = roll_pitch_from_specific_force(f_mean)
        q = quat_from_euler(roll, pitch, self.heading_rad)
        if static:
            gyro_bias = g.mean(axis=0)
            gravity = float(np.linalg.norm(f_mean)) if opts.estimate_gravity else self.nominal_gravity
            sigma_rp = math.radians(opts.sigma_attitude_static_deg)
            # The mean of the window pins the bias far better than the prior does; its sigma from
            # the scatter of the block means (vibration makes neighbouring samples correlated).
            sigma_bg = max(float(g_means.std(axis=0).max()) / math.sqrt(len(g_means)), 1e-5)
        else:
            gyro_bias = np.zeros(3)
            gravity = self.nominal_gravity
            sigma_rp = math.radians(opts.sigma_attitude_moving_deg)
            sigma_bg = opts.sigma_gyro_bias
        return InitialAttitude(t_ns, q, gyro_bias, gravity, static, sigma_rp, sigma_bg, len(g))
