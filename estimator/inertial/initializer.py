"""Initial attitude from the IMU: roll and pitch from gravity, gyro bias, gravity magnitude.

The thesis calibrates before each run from a static stretch (section 5.2). Here the filter
waits for a window in which the IMU is still; if none comes within ``max_wait_s`` (the vehicle
is already moving, as at the start of EuRoC MH01) it starts from the mean of the last window
with wider uncertainties instead of waiting forever. A moving window's specific forces are
turned into the frame of its last sample by the gyro before they are averaged (a vehicle that
rolls by 10° within the window would otherwise be started at its mean attitude, not its last);
the mean still holds the vehicle's own mean acceleration, which the start's tilt sigma must
carry (``start.py`` measures it from the GPS).

A stated heading is the vehicle's at the first sample; the start comes up to ``max_wait_s``
later, so the heading is carried there by the gyro, its sigma grown by what the gyro bias
may have turned meanwhile.

"Still" means no motion, not no vibration: a helicopter on the pad with its rotor turning
shakes its IMU by ±0.5 m/s² at tens of hertz while it does not move at all. Stillness is
therefore judged on means over ``average_s`` (0.1 s: motion of a vehicle lies below 5 Hz,
vibration above), and the bias' uncertainty comes from the scatter of those means.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from vtolpose.estimator.core.columns import make_room
from vtolpose.estimator.core.rotation import quat_from_euler, quat_to_rot, so3_exp
from vtolpose.estimator.inertial.motion_alignment import integrate


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
    window_s: float = 0.0  # the span of the window the tilt was taken from
    sigma_tilt_turned: float = 0.0  # rad: the part of the tilt's sigma an unknown gyro bias gives a moving window
    heading_drift_sigma: float = 0.0  # rad: what the gyro may have turned the stated heading by since the first sample

    def with_mean_acceleration(self, sigma_rad: float) -> InitialAttitude:
        """A moving start whose window's mean acceleration was measured: that, not the configured guess, and the
        gyro's part make its tilt sigma."""
        return replace(self, sigma_roll_pitch=math.hypot(sigma_rad, self.sigma_tilt_turned))


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


class SampleWindow:
    """The samples of a sliding time window kept in one array each (times, gyro, accel rows), oldest first:
    the window is judged at every sample, and views of it cost nothing where stacking a queue of rows
    costs its length each time."""

    def __init__(self, capacity: int = 256) -> None:
        self._t = np.empty(capacity, np.int64)
        self._rows = np.empty((capacity, 6))  # gyro, accel
        self._start = self._end = 0

    def __len__(self) -> int:
        return self._end - self._start

    def append(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray) -> None:
        if self._end == len(self._t):
            (self._t, self._rows), self._start, self._end = make_room((self._t, self._rows), self._start, self._end, 1)
        self._t[self._end] = t_ns
        self._rows[self._end, :3] = gyro
        self._rows[self._end, 3:] = accel
        self._end += 1

    def drop_older(self, span_ns: int) -> None:
        """Forget the oldest samples while the window spans more than ``span_ns``."""
        t, last = self._t, int(self._t[self._end - 1])
        while last - int(t[self._start]) > span_ns:
            self._start += 1

    def first_t(self) -> int:
        return int(self._t[self._start])

    def last_t(self) -> int:
        return int(self._t[self._end - 1])

    def last_gyro(self) -> np.ndarray:
        return self._rows[self._end - 1, :3]

    @property
    def times(self) -> np.ndarray:
        return self._t[self._start:self._end]

    @property
    def gyro(self) -> np.ndarray:
        """A copy (C-ordered), as the window's rows stacked."""
        return self._rows[self._start:self._end, :3].copy()

    @property
    def accel(self) -> np.ndarray:
        return self._rows[self._start:self._end, 3:].copy()


class StaticInitializer:
    """Feed IMU samples; returns an :class:`InitialAttitude` once it can."""

    def __init__(self, options: InitOptions, nominal_gravity: float, heading_rad: float = 0.0) -> None:
        self.options = options
        self.nominal_gravity = nominal_gravity
        self.heading_rad = heading_rad
        self._window = SampleWindow()
        self._first_t: int | None = None
        self._turned = np.eye(3)  # the body's rotation from the first sample to the last, by the raw gyro
        self._turned_s = 0.0  # over how long

    def add(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray) -> InitialAttitude | None:
        """Returns the initial attitude once a still window exists, or once ``max_wait_s`` has passed
        without one (then from the last window, less certain)."""
        opts = self.options
        if self._first_t is None:
            self._first_t = t_ns
        self.keep(t_ns, gyro, accel)
        window_ns = int(opts.static_window_s * 1e9)
        window = self._window
        full = window.last_t() - window.first_t() >= 0.95 * window_ns and len(window) >= 10
        if not full:
            return None
        g, a, t = window.gyro, window.accel, window.times
        g_means, a_means = block_means(t, g, opts.average_s), block_means(t, a, opts.average_s)
        static = bool(np.all(g_means.std(axis=0) < opts.gyro_std_max) and np.all(a_means.std(axis=0) < opts.accel_std_max))
        timed_out = t_ns - self._first_t >= int(opts.max_wait_s * 1e9)
        if not (static or timed_out):
            return None
        return self._solve(t_ns, g, a, g_means, static)

    def keep(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Only hold the sample in the window (no judgement): for :meth:`latest` later."""
        window_ns = int(self.options.static_window_s * 1e9)
        window = self._window
        if len(window):
            dt = (t_ns - window.last_t()) * 1e-9
            self._turned = self._turned @ so3_exp(window.last_gyro() * dt)
            self._turned_s += dt
        window.append(t_ns, gyro, accel)
        window.drop_older(window_ns)

    def latest(self) -> InitialAttitude | None:
        """A moving start from the window as it is now (None while it holds fewer than ten samples)."""
        window = self._window
        if len(window) < 10:
            return None
        g = window.gyro
        return self._solve(window.last_t(), g, window.accel, block_means(window.times, g, self.options.average_s), False)

    def as_moving(self, init: InitialAttitude) -> InitialAttitude:
        """``init`` judged again as a moving start (the GPS says the "still" window was steady motion)."""
        window = self._window
        g = window.gyro
        return self._solve(init.t_ns, g, window.accel, block_means(window.times, g, self.options.average_s), False)

    def _solve(self, t_ns: int, g: np.ndarray, a: np.ndarray, g_means: np.ndarray, static: bool) -> InitialAttitude:
        opts = self.options
        t = self._window.times.copy()
        span = (t[-1] - t[0]) * 1e-9
        if static:
            f_mean = a.mean(axis=0)
            gyro_bias = g.mean(axis=0)
            gravity = float(np.linalg.norm(f_mean)) if opts.estimate_gravity else self.nominal_gravity
            sigma_rp = math.radians(opts.sigma_attitude_static_deg)
            # The mean of the window pins the bias far better than the prior does; its sigma from
            # the scatter of the block means (vibration makes neighbouring samples correlated).
            sigma_bg = max(float(g_means.std(axis=0).max()) / math.sqrt(len(g_means)), 1e-5)
        else:
            gyro_bias = np.zeros(3)
            gravity = self.nominal_gravity
            sigma_bg = opts.sigma_gyro_bias
            f_mean = specific_force_in_last_frame(t, g, a)
            # The mean sample is half a window older than the last: an unknown gyro bias turned it by that much.
            # The vehicle's own mean acceleration is the caller's to add (the GPS measures it).
            turned = sigma_bg * 0.5 * span
            sigma_rp = math.hypot(math.radians(opts.sigma_attitude_moving_deg), turned)
        roll, pitch = roll_pitch_from_specific_force(f_mean)
        heading, drift = self._heading_now(roll, pitch, gyro_bias, sigma_bg, sigma_rp)
        q = quat_from_euler(roll, pitch, heading)
        return InitialAttitude(t_ns, q, gyro_bias, gravity, static, sigma_rp, sigma_bg, len(g), span,
                               0.0 if static else turned, drift)

    def stated_heading_now(self) -> tuple[float, float]:
        """The stated heading carried to the last sample held and the sigma of its drift since the first, as for a
        moving start (no bias known; the tilt from the plain mean, which moves a heading carried through a turn
        about down only to second order): the heading a visual start at that sample takes as its gauge."""
        if not len(self._window):
            return self.heading_rad, 0.0
        opts = self.options
        roll, pitch = roll_pitch_from_specific_force(np.mean(self._window.accel, axis=0))
        return self._heading_now(roll, pitch, np.zeros(3), opts.sigma_gyro_bias, math.radians(opts.sigma_attitude_moving_deg))

    def _heading_now(self, roll: float, pitch: float, gyro_bias: np.ndarray, sigma_bg: float,
                     sigma_rp: float) -> tuple[float, float]:
        """The stated heading (the first sample's) carried to the last sample by the gyro, and the sigma of what
        it may have turned by: the bias' uncertainty over the time since, and the tilt's through the turn
        (nothing for a turn about down, all of it for a roll of 90°)."""
        elapsed = self._turned_s
        turned = self._turned @ so3_exp(-gyro_bias * elapsed)  # first order in the bias: enough over seconds

        def carried(roll: float, pitch: float) -> float:
            first = quat_to_rot(quat_from_euler(roll, pitch, 0.0)) @ turned.T  # the first sample's attitude
            return self.heading_rad - math.atan2(first[1, 0], first[0, 0])

        heading = carried(roll, pitch)
        step = 1e-4
        slopes = [(carried(roll + step * d[0], pitch + step * d[1]) - heading) / step for d in ((1, 0), (0, 1))]
        drift = math.hypot(sigma_bg * elapsed, sigma_rp * math.hypot(*slopes))
        return math.atan2(math.sin(heading), math.cos(heading)), drift


def specific_force_in_last_frame(t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """The window's mean specific force in the body frame of its last sample: each sample turned there by the
    gyro (uncorrected: a moving start knows no bias), so that the attitude found is the last sample's."""
    t = (t_ns - t_ns[0]) * 1e-9
    dt = np.diff(t)
    turned = integrate(t, gyro[:-1] * dt[:, None], accel[:-1] * dt[:, None], np.zeros(3), t)
    in_first = np.einsum("nij,nj->ni", turned.R, accel)
    return turned.R[-1].T @ in_first.mean(axis=0)
