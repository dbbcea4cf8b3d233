"""IMU calibration from a static stretch (thesis 5.2): gravity, gyro bias, roll/pitch, noise.

At rest the gyro reads its bias and the accelerometer reads ``-R^T g_W``: its magnitude is the
local gravity (as this accelerometer sees it; the bias along the vertical is inseparable from
g in one position, which is why the thesis estimates g before each run) and its direction gives
roll and pitch. The scatter around those means, through an Allan deviation, gives the noise
densities the filter needs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from vtolpose.estimator.calibration.allan import AllanCurve, AllanFit, allan_deviation, fit_noise
from vtolpose.estimator.inertial.initializer import roll_pitch_from_specific_force
from vtolpose.estimator.calibration.static_detection import (
    NoStaticStretchError, StaticOptions, StaticStretch, find_static_stretches, reject_moving, require_static_stretch,
    rest_advice,
)


@dataclass(frozen=True, slots=True)
class ImuCalibrationResult:
    """What one static stretch says about the IMU (body FRD axes, SI units)."""

    stretch: StaticStretch
    stretches: list[StaticStretch]
    rate_hz: float
    gravity: float
    accel_mean: np.ndarray
    gyro_bias: np.ndarray
    gyro_bias_sigma: np.ndarray  # 1σ of the mean, from the white noise
    roll_rad: float
    pitch_rad: float
    curve: AllanCurve  # channels: gyro x y z, accel x y z
    gyro_fits: tuple[AllanFit, AllanFit, AllanFit]
    accel_fits: tuple[AllanFit, AllanFit, AllanFit]
    notes: list[str] = field(default_factory=list)

    def figure(self, sensor: str, name: str) -> np.ndarray | None:
        """Per-axis ``white_noise``, ``bias_instability`` or ``random_walk`` of ``gyro``/``accel``;
        None if any axis lacks it."""
        fits = self.gyro_fits if sensor == "gyro" else self.accel_fits
        values = [getattr(f, name) for f in fits]
        return None if any(v is None for v in values) else np.array(values, dtype=float)


def calibrate_imu(
    t_ns: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    static: StaticOptions = StaticOptions(),
    min_fit_tau_s: float = 0.0,
    positions: tuple[np.ndarray, np.ndarray] | None = None,
) -> ImuCalibrationResult:
    """Calibrate from the longest static stretch of a body-frame IMU record.

    Raises :class:`vtolpose.estimator.calibration.static_detection.NoStaticStretchError` when there is none.
    ``min_fit_tau_s`` leaves out of the Allan fit the short τ that a sensor's internal filter
    flattens. ``positions`` (fix times [ns], NED positions), when the record has them, rule out
    stretches of steady straight flight, which the IMU alone cannot tell from rest.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    gyro, accel = np.asarray(gyro, dtype=float), np.asarray(accel, dtype=float)
    stretches = find_static_stretches(t_ns, gyro, accel, static)
    if positions is not None and stretches:
        stretches, moving = reject_moving(stretches, *positions)
        if not stretches:
            worst = max(speed for _, speed in moving)
            raise NoStaticStretchError(
                f"the IMU is quiet in {len(moving)} stretch(es) but the position fixes show the vehicle moving (up to "
                f"{worst:.1f} m/s: steady flight, not rest). {rest_advice(static.min_duration_s)}")
    stretch = stretches[0] if stretches else require_static_stretch(t_ns, gyro, accel, static)  # raises, explaining
    sl = slice(stretch.start, stretch.stop)
    g, a, t = gyro[sl], accel[sl], t_ns[sl]
    dt = np.diff(t) * 1e-9
    rate_hz = 1.0 / float(np.median(dt))
    notes = []
    gaps = int(np.count_nonzero(dt > 1.5 / rate_hz))
    if gaps:
        notes.append(f"{gaps} gap(s) in the stretch: the Allan deviation assumes even sampling, its figures are approximate")
    f_mean = a.mean(axis=0)
    roll, pitch = roll_pitch_from_specific_force(f_mean)
    curve = allan_deviation(np.hstack([g, a]), rate_hz)
    fits = [fit_noise(curve, k, min_fit_tau_s) for k in range(6)]
    bias = g.mean(axis=0)
    duration = len(g) / rate_hz
    bias_sigma = np.array([f.white_noise for f in fits[:3]]) / math.sqrt(duration)
    notes.extend(_vibration_notes(curve))
    for sensor, group in (("gyro", fits[:3]), ("accel", fits[3:])):
        if any(f.random_walk is None for f in group):
            bound = max(f.random_walk_bound for f in group)
            notes.append(
                f"{sensor} bias random walk not measurable from {duration:.0f} s of rest (the Allan curve does not turn "
                f"upward; it is at most {bound:.2g} per sqrt(s)): record an hour or more of rest to measure it")
        if any(f.bias_instability_is_bound for f in group):
            notes.append(f"{sensor} bias instability is an upper bound (the Allan curve still falls at the longest "
                         "reliable cluster time): record longer")
    return ImuCalibrationResult(
        stretch=stretch,
        stretches=stretches,
        rate_hz=rate_hz,
        gravity=float(np.linalg.norm(f_mean)),
        accel_mean=f_mean,
        gyro_bias=bias,
        gyro_bias_sigma=bias_sigma,
        roll_rad=roll,
        pitch_rad=pitch,
        curve=curve,
        gyro_fits=tuple(fits[:3]),
        accel_fits=tuple(fits[3:]),
        notes=notes,
    )


def _vibration_notes(curve: AllanCurve) -> list[str]:
    """White noise only falls with τ; a curve that first rises holds a periodic disturbance
    (engine, rotor, fan) whose period is about 2.7 τ of the peak. The white-noise figures then
    include it — right for a vehicle that vibrates in flight, too high for a bench."""
    notes = []
    short = curve.tau <= 1.0
    for k, name in enumerate(("gyro x", "gyro y", "gyro z", "accel x", "accel y", "accel z")):
        sigma = curve.adev[short, k]
        i = int(np.argmax(sigma))
        if sigma[i] > 1.2 * sigma[0]:
            notes.append(f"{name}: the Allan curve rises to tau = {curve.tau[short][i]:.3g} s: a vibration near "
                         f"{0.371 / curve.tau[short][i]:.1f} Hz on the rest stretch; its white noise includes it")
    return notes
