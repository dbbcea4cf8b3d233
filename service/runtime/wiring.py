"""From validated configuration to typed values: the sections drivers and outputs take, and the
estimator's options (one place, no guessing).

This module and ``config/`` are the only readers of the flat ``{"a.b": value}`` dict; everything
else takes a section or an option object built here.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from typing import Any

import numpy as np

from vtolpose.config import ConfigError, get
from vtolpose.config.sections import Sections, build_sections
from vtolpose.estimator import (
    AssociationOptions, Calibration, CameraOptions, FeatureOptions, FilterOptions, FrameQualityOptions,
    HeadingBankOptions, HealthOptions, ImuNoise, ImuRange, InitOptions, MapOptions, STANDARD_GRAVITY,
    MountingOptions, StillnessOptions, TimeOffsetOptions, VisualInertialOptions,
)

NOISE_KEYS = ("gyro_noise_density", "gyro_random_walk", "accel_noise_density", "accel_random_walk")


def config_sections(cfg: dict[str, Any]) -> Sections:
    """The typed sections of the validated ``cfg``, for the drivers, the outputs and the runtime."""
    return build_sections(cfg)


def with_gps_origin(sections: Sections, origin: tuple[float, float, float]) -> Sections:
    """``sections`` with ``sensors.gps.origin`` set: a live run takes the vehicle calibration's origin as the
    one local frame when the configuration gives none."""
    gps = dataclasses.replace(sections.sensors.gps, origin=origin)
    return dataclasses.replace(sections, sensors=dataclasses.replace(sections.sensors, gps=gps))


def estimator_variant(cfg: dict[str, Any]) -> str:
    """``estimator.variant``: the state model the filter runs (reports name it)."""
    return cfg["estimator.variant"]


def imu_range(cfg: dict[str, Any]) -> ImuRange:
    """``estimator.imu.gyro_range_dps`` and ``accel_range_g`` in SI (rad/s, m/s^2)."""
    return ImuRange(math.radians(cfg["estimator.imu.gyro_range_dps"]), cfg["estimator.imu.accel_range_g"] * STANDARD_GRAVITY)


def imu_noise_override(cfg: dict[str, Any], fallback: ImuNoise) -> ImuNoise | None:
    """Noise from config where given, the calibration's for keys left null; None if all null."""
    given = get(cfg, "estimator.imu.noise")
    if all(given[k] is None for k in NOISE_KEYS):
        return None
    return ImuNoise(*(given[k] if given[k] is not None else getattr(fallback, k) for k in NOISE_KEYS))


def init_options(cfg: dict[str, Any]) -> InitOptions:
    values = get(cfg, "estimator.init")
    gravity = values.pop("estimate_gravity")
    # 'auto': the thesis model has no accelerometer bias state, so the still window's |f|
    # (gravity plus the vertical bias) is its best g; the biases model estimates that bias.
    values["estimate_gravity"] = cfg["estimator.variant"] == "thesis" if gravity == "auto" else gravity == "true"
    return InitOptions(**values)


def thesis_noise(cfg: dict[str, Any], noise: ImuNoise) -> ImuNoise:
    """The thesis model's tuned white noise; it has no bias states, so no bias random walks."""
    return ImuNoise(
        gyro_noise_density=np.maximum(noise.gyro_noise_density, cfg["estimator.thesis.gyro_noise_density"]),
        gyro_random_walk=noise.gyro_random_walk,
        accel_noise_density=np.maximum(noise.accel_noise_density, cfg["estimator.thesis.accel_noise_density"]),
        accel_random_walk=noise.accel_random_walk,
    )


def filter_options(cfg: dict[str, Any], calibration_noise: ImuNoise) -> FilterOptions:
    noise = imu_noise_override(cfg, calibration_noise)
    if cfg["estimator.variant"] == "thesis":
        noise = thesis_noise(cfg, noise or calibration_noise)
    return FilterOptions(
        variant=cfg["estimator.variant"],
        heading_source=cfg["estimator.heading.source"],
        heading_deg=cfg["estimator.heading.deg"],
        gps_gate=cfg["estimator.gps.gate_chi2"],
        gps_sigma_floor_m=cfg["estimator.gps.sigma_floor_m"],
        max_imu_gap_s=cfg["estimator.imu.max_gap_s"],
        max_filter_rate_hz=cfg["estimator.imu.max_filter_rate_hz"],
        noise=noise,
        init=init_options(cfg),
        align=HeadingBankOptions(**get(cfg, "estimator.alignment")),
        unaligned_accel_noise=cfg["estimator.unaligned.accel_noise"],
        level_sigma=cfg["estimator.unaligned.level_sigma"],
        gps_reset_after_s=cfg["estimator.gps_reset_after_s"],
        still=StillnessOptions(**get(cfg, "estimator.stillness")),
        camera=camera_options(cfg),
        visual_inertial=VisualInertialOptions(**get(cfg, "estimator.visual_inertial")),  # start in motion, no GPS
        health=HealthOptions(**get(cfg, "estimator.health")),  # sensor loss, divergence, IMU gaps
    )


def camera_options(cfg: dict[str, Any]) -> CameraOptions:
    """``estimator.camera.*``: association keys to AssociationOptions, map keys to MapOptions."""
    values = get(cfg, "estimator.camera")
    assoc = {k: values.pop(k) for k in ("gate_px", "ratio_test", "max_descriptor_distance", "max_hamming_fraction", "chi2")}
    pixel_sigma = values.pop("pixel_sigma")
    working_width = values.pop("working_width")
    time_offset = TimeOffsetOptions(values.pop("estimate_time_offset"), values.pop("time_offset_sigma_s"))
    mounting = MountingOptions(values.pop("estimate_extrinsics"), values.pop("extrinsic_rotation_sigma_deg"),
                               values.pop("extrinsic_translation_sigma_m"))
    return CameraOptions(pixel_sigma=pixel_sigma, association=AssociationOptions(**assoc), map=MapOptions(**values),
                         time_offset=time_offset, mounting=mounting, working_width=working_width)


def feature_options(cfg: dict[str, Any]) -> FeatureOptions:
    values = get(cfg, "features")
    quality = {k: values.pop(k) for k in ("black_level", "saturated_level", "saturated_fraction", "min_texture_std")}
    # The camera's working width is the estimator's (it scales the intrinsics to it): one key for both sides.
    return FeatureOptions(**values, quality=FrameQualityOptions(**quality), working_width=cfg["estimator.camera.working_width"])


_CAMERA_FIELDS = ("width", "height", "fx", "fy", "cx", "cy")
_DISTORTION = ("k1", "k2", "p1", "p2", "k3")


def calibration_with_overrides(cfg: dict[str, Any], calibration: Calibration) -> Calibration:
    """The dataset's (or vehicle's) calibration with what ``vtolpose calibrate`` measured on top.

    The config's ``calibration:`` keys that are not null replace the matching values; the camera
    keys need the calibration to have a camera (its mounting R_BC, t_BC is not in the section).
    """
    cal = copy.deepcopy(calibration)
    c = get(cfg, "calibration")
    if c["imu.gravity"] is not None:
        cal.imu.gravity = c["imu.gravity"]
    # The Allan figures become the sensor's noise model (``estimator.imu.noise.*``, when set, still
    # overrides them: in-flight vibration is not in a bench recording). The gyro bias and the attitude
    # at rest are a record of the calibration run only: the filter measures both again at every start.
    for key in ("gyro_noise_density", "gyro_random_walk", "accel_noise_density", "accel_random_walk"):
        if c[f"imu.{key}"] is not None:
            setattr(cal.imu.noise, key, np.asarray(c[f"imu.{key}"], dtype=float))
    if c["gps.time_offset_s"] is not None:
        cal.gps.time_offset_s = c["gps.time_offset_s"]
    if c["gps.lever_arm_b"] is not None:
        cal.gps.lever_arm_b = np.asarray(c["gps.lever_arm_b"], dtype=float)
    camera_keys = [k for k in (*_CAMERA_FIELDS, *_DISTORTION, "time_offset_s") if c[f"camera.{k}"] is not None]
    if camera_keys:
        if cal.camera is None:
            raise ConfigError(
                f"keys calibration.camera.{', calibration.camera.'.join(camera_keys)}: the calibration has no camera "
                "block to apply them to (its mounting R_BC, t_BC comes from dataset.yaml)"
            )
        for k in _CAMERA_FIELDS:
            if c[f"camera.{k}"] is not None:
                setattr(cal.camera, k, type(getattr(cal.camera, k))(c[f"camera.{k}"]))
        radtan_keys = [k for k in _DISTORTION if c[f"camera.{k}"] is not None]
        if radtan_keys and cal.camera.model != "radtan":
            raise ConfigError(
                f"keys calibration.camera.{', calibration.camera.'.join(radtan_keys)}: radial-tangential coefficients, "
                f"but the camera in dataset.yaml is {cal.camera.model} (set its distortion there)"
            )
        for i, k in enumerate(_DISTORTION):
            if c[f"camera.{k}"] is not None:
                cal.camera.distortion[i] = c[f"camera.{k}"]
        if c["camera.time_offset_s"] is not None:
            cal.camera.time_offset_s = c["camera.time_offset_s"]
    return cal
