"""Types and limits of every configuration key; ``default.yaml`` holds the values.

A key missing here but present in ``default.yaml`` (or the reverse) is a programming error
caught by the tests, so the two cannot drift apart.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Field:
    kind: str  # bool | int | float | str | list | matrix3 | vector3
    nullable: bool = False
    choices: tuple = ()
    minimum: float | None = None
    maximum: float | None = None
    items: tuple = ()  # allowed list items (for kind 'list')
    positive: bool = False


POS = Field("float", positive=True)
NONNEG = Field("float", minimum=0.0)
NOISE = Field("float", nullable=True, minimum=0.0)

SCHEMA: dict[str, Field] = {
    "vehicle.name": Field("str"),
    "vehicle.system_id": Field("int", minimum=1, maximum=255),
    "estimator.variant": Field("str", choices=("thesis", "biases")),
    "estimator.heading.source": Field("str", choices=("auto", "dataset", "gps")),
    "estimator.heading.deg": Field("float", nullable=True, minimum=-360.0, maximum=360.0),
    "estimator.gps.gate_chi2": Field("float", nullable=True, positive=True),
    "estimator.gps.sigma_floor_m": POS,
    "estimator.gps_reset_after_s": POS,
    "estimator.imu.max_gap_s": POS,
    "estimator.imu.max_filter_rate_hz": POS,
    "estimator.imu.noise.gyro_noise_density": NOISE,
    "estimator.imu.noise.gyro_random_walk": NOISE,
    "estimator.imu.noise.accel_noise_density": NOISE,
    "estimator.imu.noise.accel_random_walk": NOISE,
    "estimator.thesis.accel_noise_density": POS,
    "estimator.thesis.gyro_noise_density": POS,
    "estimator.init.static_window_s": POS,
    "estimator.init.max_wait_s": POS,
    "estimator.init.gyro_std_max": POS,
    "estimator.init.accel_std_max": POS,
    "estimator.init.estimate_gravity": Field("str", choices=("auto", "true", "false")),
    "estimator.init.sigma_attitude_static_deg": POS,
    "estimator.init.sigma_attitude_moving_deg": POS,
    "estimator.init.sigma_heading_known_deg": POS,
    "estimator.init.sigma_velocity_static": POS,
    "estimator.init.sigma_velocity_moving": POS,
    "estimator.init.sigma_gyro_bias": POS,
    "estimator.init.sigma_accel_bias": POS,
    "estimator.stillness.enabled": Field("bool"),
    "estimator.stillness.chunk_s": POS,
    "estimator.stillness.gyro_std_max": POS,
    "estimator.stillness.accel_std_max": POS,
    "estimator.stillness.gravity_tolerance": POS,
    "estimator.stillness.speed_max": POS,
    "estimator.stillness.zupt_sigma": POS,
    "estimator.unaligned.accel_noise": NONNEG,
    "estimator.unaligned.level_sigma": POS,
    "estimator.alignment.window_s": POS,
    "estimator.alignment.min_window_s": POS,
    "estimator.alignment.solve_every_s": POS,
    "estimator.alignment.max_sigma_tilt_deg": POS,
    "estimator.alignment.max_sigma_heading_deg": POS,
    "estimator.alignment.max_residual_ratio": POS,
    "replay.sensors": Field("list", items=("imu", "gps", "camera")),
    "replay.nees_rate_hz": POS,
}
