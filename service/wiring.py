"""From validated configuration to the estimator's typed options (one place, no guessing)."""

from __future__ import annotations

from typing import Any

from config import get
from estimator.calibration import ImuNoise
from estimator.filter import FilterOptions
from estimator.heading import AlignOptions
from estimator.initializer import InitOptions

NOISE_KEYS = ("gyro_noise_density", "gyro_random_walk", "accel_noise_density", "accel_random_walk")


def imu_noise_override(cfg: dict[str, Any], fallback: ImuNoise) -> ImuNoise | None:
    """Noise from config where given, the calibration's for keys left null; None if all null."""
    given = get(cfg, "estimator.imu.noise")
    if all(given[k] is None for k in NOISE_KEYS):
        return None
    return ImuNoise(*(given[k] if given[k] is not None else getattr(fallback, k) for k in NOISE_KEYS))


def filter_options(cfg: dict[str, Any], calibration_noise: ImuNoise) -> FilterOptions:
    return FilterOptions(
        variant=cfg["estimator.variant"],
        heading_source=cfg["estimator.heading.source"],
        heading_deg=cfg["estimator.heading.deg"],
        gps_gate=cfg["estimator.gps.gate_chi2"],
        gps_sigma_floor_m=cfg["estimator.gps.sigma_floor_m"],
        max_imu_gap_s=cfg["estimator.imu.max_gap_s"],
        noise=imu_noise_override(cfg, calibration_noise),
        init=InitOptions(**get(cfg, "estimator.init")),
        align=AlignOptions(**get(cfg, "estimator.alignment")),
    )
