"""IMU error model: white noise, bias random walk and a turn-on bias on top of exact readings.

Default values are of the class of the thesis' Crossbow IMU400CC, a MEMS unit of the early
2000s (chosen by order of magnitude, not copied from a datasheet; all configurable):
- gyro white noise 3e-4 rad/s/√Hz ≈ 1 °/√h angle random walk,
- gyro bias random walk 2e-5 rad/s²/√Hz: the bias wanders ≈ 0.03 °/s in ten minutes,
- accel white noise 2e-3 m/s²/√Hz ≈ 0.12 m/s/√h velocity random walk,
- accel bias random walk 3e-4 m/s³/√Hz: ≈ 7 mm/s² in ten minutes,
- turn-on biases 0.2 °/s (gyro) and 0.015 m/s² (accel), new at every power-up. The
  accelerometer figure is the residual after the pre-flight calibration the thesis does before
  every run (section 5.2: gravity and a multi-position bias calibration); the raw turn-on
  bias of such a unit is several times larger. The gyro bias is measured on the pad.
- rotor vibration, off by default: a tone at ``vibration_hz`` and its second harmonic on every
  axis, of the stated RMS. It is motion of micrometres, so the truth leaves it out; the IMU
  senses it in full (and aliases it, as a real one without an anti-alias filter does), and the
  noise densities handed to the estimator do not include it, as a bench Allan variance would not.
Densities follow the Kalibr/EuRoC convention (see ``vtolpose.estimator.core.calibration.ImuNoise``):
per-sample white std = density·√rate, per-step bias increment std = random_walk·√dt.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vtolpose.estimator.core.calibration import ImuNoise


@dataclass(frozen=True, slots=True)
class ImuErrorModel:
    """Sample rate and error parameters of the simulated IMU (isotropic, SI units)."""

    rate_hz: float = 125.0
    gyro_noise_density: float = 3.0e-4
    gyro_random_walk: float = 2.0e-5
    accel_noise_density: float = 2.0e-3
    accel_random_walk: float = 3.0e-4
    gyro_turn_on_bias_std: float = float(np.deg2rad(0.2))
    accel_turn_on_bias_std: float = 0.015
    vibration_hz: float = 0.0  # rotor frequency of the vibration term
    vibration_accel_rms: float = 0.0  # per axis [m/s²]
    vibration_gyro_rms: float = 0.0  # per axis [rad/s]

    def __post_init__(self) -> None:
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0.0):
            raise ValueError(f"imu rate_hz must be positive, got {self.rate_hz}")
        for name in (
            "gyro_noise_density",
            "gyro_random_walk",
            "accel_noise_density",
            "accel_random_walk",
            "gyro_turn_on_bias_std",
            "accel_turn_on_bias_std",
            "vibration_hz",
            "vibration_accel_rms",
            "vibration_gyro_rms",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0.0):
                raise ValueError(f"imu {name} must be finite and non-negative, got {value}")
        if (self.vibration_accel_rms or self.vibration_gyro_rms) and not self.vibration_hz:
            raise ValueError("imu vibration needs its rotor frequency vibration_hz")

    @classmethod
    def perfect(cls, rate_hz: float = 125.0) -> "ImuErrorModel":
        """No noise and no bias: readings are the exact derivatives of the truth."""
        return cls(rate_hz, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    def noise(self) -> ImuNoise:
        """The densities as the estimator's calibration wants them."""
        return ImuNoise.isotropic(
            self.gyro_noise_density, self.gyro_random_walk, self.accel_noise_density, self.accel_random_walk
        )


@dataclass(frozen=True, slots=True)
class ImuErrors:
    """Measured values and the biases inside them, at the IMU sample times."""

    gyro: np.ndarray
    accel: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray


def _random_walk(start: np.ndarray, step_std: float, n: int, rng: np.random.Generator) -> np.ndarray:
    steps = rng.standard_normal((n - 1, 3)) * step_std
    return start + np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])


def corrupt_imu(
    omega_b: np.ndarray, specific_force_b: np.ndarray, model: ImuErrorModel, rng: np.random.Generator
) -> ImuErrors:
    """Add turn-on bias, bias random walk and white noise to exact readings (N, 3) each.

    Draw order is fixed (turn-on biases, gyro walk, accel walk, gyro noise, accel noise, then the
    vibration's phases only when it is on), so a seed always gives the same errors for the same
    number of samples, and a model without vibration the same ones as before it existed.
    """
    n = len(omega_b)
    if n == 0:
        empty = np.zeros((0, 3))
        return ImuErrors(empty, empty.copy(), empty.copy(), empty.copy())
    dt = 1.0 / model.rate_hz
    b_g0 = rng.standard_normal(3) * model.gyro_turn_on_bias_std
    b_a0 = rng.standard_normal(3) * model.accel_turn_on_bias_std
    b_g = _random_walk(b_g0, model.gyro_random_walk * np.sqrt(dt), n, rng)
    b_a = _random_walk(b_a0, model.accel_random_walk * np.sqrt(dt), n, rng)
    white_g = rng.standard_normal((n, 3)) * model.gyro_noise_density * np.sqrt(model.rate_hz)
    white_a = rng.standard_normal((n, 3)) * model.accel_noise_density * np.sqrt(model.rate_hz)
    gyro, accel = omega_b + b_g + white_g, specific_force_b + b_a + white_a
    if model.vibration_accel_rms or model.vibration_gyro_rms:
        t = np.arange(n) * dt
        gyro = gyro + rotor_vibration(t, model.vibration_hz, model.vibration_gyro_rms, rng)
        accel = accel + rotor_vibration(t, model.vibration_hz, model.vibration_accel_rms, rng)
    return ImuErrors(gyro, accel, b_g, b_a)


VIBRATION_HARMONICS = (1.0, 0.5)  # relative amplitudes of the rotor tone and its second harmonic


def rotor_vibration(t_s: np.ndarray, rotor_hz: float, rms: float, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) vibration of ``rms`` per axis: the rotor tone and its harmonic, random phases per axis."""
    weights = np.array(VIBRATION_HARMONICS)
    amplitude = rms * np.sqrt(2.0) / np.linalg.norm(weights)  # a sine of amplitude a has RMS a/√2
    phases = rng.uniform(0.0, 2.0 * np.pi, (len(weights), 3))
    out = np.zeros((len(t_s), 3))
    for h, (w, phase) in enumerate(zip(weights, phases), start=1):
        out += amplitude * w * np.sin(2.0 * np.pi * h * rotor_hz * t_s[:, None] + phase)
    return out


def bias_at(t_imu_ns: np.ndarray, bias: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
    """Biases at other times (e.g. the truth's): linear between IMU samples, held at the ends.

    The random walk is defined at the IMU instants; linear interpolation is its continuous-time
    reading used for the truth, and it draws nothing, so the truth rate never alters the IMU.
    """
    if len(t_imu_ns) == 0:
        return np.zeros((len(t_ns), 3))
    t0 = int(t_imu_ns[0])
    x, xp = (np.asarray(t_ns, dtype=np.int64) - t0).astype(float), (np.asarray(t_imu_ns) - t0).astype(float)
    return np.stack([np.interp(x, xp, bias[:, k]) for k in range(3)], axis=-1)
