"""``dataset.yaml`` ⇄ :class:`vtolpose.estimator.core.calibration.Calibration`, with errors that name the key.

A typo in a calibration file must not turn into a silently default lever arm, so unknown keys
are errors too. Vectors may be written as scalars where that is natural (isotropic noise).
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from vtolpose.config.yaml_limits import BoundedLoader, UnsafeYaml, read_bounded
from vtolpose.estimator.core.calibration import (
    CAMERA_MODELS,
    STANDARD_GRAVITY,
    Calibration,
    CameraCalibration,
    GpsCalibration,
    ImuCalibration,
    ImuNoise,
)
from vtolpose.estimator.core.rotation import is_proper_rotation

DATASET_FORMAT = "vtolpose-dataset/1"
_TOP_KEYS = {"format", "name", "description", "imu", "gps", "truth", "init", "camera"}
_NOISE_KEYS = ("gyro_noise_density", "gyro_random_walk", "accel_noise_density", "accel_random_walk")
_CAMERA_KEYS = {"width", "height", "fx", "fy", "cx", "cy", "model", "distortion", "R_BC", "t_BC", "rate_hz", "time_offset_s"}


def _finite(x: int | float) -> bool:
    """Finite as a float (a YAML integer has no size limit: 10**400 is no float)."""
    try:
        return math.isfinite(x)
    except OverflowError:
        return False


class CalibrationError(ValueError):
    """A calibration file that cannot be used; the message names the file and the key."""


_OPENCV_HEADER = re.compile(r"\A\ufeff?%YAML:\d+\.\d+[ \t]*(?:\r?\n|\Z)")


class _OpenCvSafeLoader(BoundedLoader):
    """The bounded SafeLoader that also reads OpenCV ``FileStorage`` matrices (``!!opencv-matrix``) as plain mappings."""


_OpenCvSafeLoader.add_constructor(
    "tag:yaml.org,2002:opencv-matrix", lambda loader, node: loader.construct_mapping(node, deep=True))


def parse_yaml_text(text: str) -> Any:
    """YAML as written by this program, or OpenCV-style: a ``%YAML:1.0`` first line (OpenCV
    ``FileStorage``, ORB-SLAM, VINS, Kimera and the EuRoC ``sensor.yaml`` files write it, PyYAML
    refuses it) is dropped, and ``!!opencv-matrix`` nodes become ``{rows, cols, dt, data}`` mappings.
    Aliases are bounded as in ``vtolpose.config.yaml_limits`` (UnsafeYaml past the bound)."""
    return yaml.load(_OPENCV_HEADER.sub("", text, count=1), Loader=_OpenCvSafeLoader)


def load_yaml_file(path: Path) -> Any:
    """The document in a small YAML file; CalibrationError names the file when it cannot be read as one
    (including a file too large, or aliases that would expand without bound: ``vtolpose.config.yaml_limits``)."""
    try:
        return parse_yaml_text(read_bounded(path))
    except UnsafeYaml as exc:
        raise CalibrationError(f"{path}: {exc}") from None
    except UnicodeDecodeError as exc:
        raise CalibrationError(f"{path}: not UTF-8 text (byte {exc.start}: {exc.reason})") from None
    except yaml.YAMLError as exc:
        raise CalibrationError(f"{path}: not valid YAML: {exc}") from None
    except RecursionError:  # PyYAML recurses per nesting level: '[[[[...' a thousand deep
        raise CalibrationError(f"{path}: nested too deeply to be YAML this program writes") from None


class YamlReader:
    """Typed access to a parsed YAML mapping; every failure names ``source: dotted.key``."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, key: str, expected: str, got: Any) -> CalibrationError:
        shown = repr(got)
        if len(shown) > 120:  # never echo a huge value in full
            shown = f"{shown[:120]}… ({len(shown)} characters)"
        return CalibrationError(f"{self.source}: {key}: expected {expected}, got {shown}")

    def mapping(self, value: Any, key: str, allowed: set[str], required: tuple[str, ...] = ()) -> dict:
        if value is None:
            value = {}
        if not isinstance(value, dict):
            raise self.fail(key, "a mapping", value)
        unknown = sorted(set(map(str, value)) - allowed)
        if unknown:
            raise CalibrationError(f"{self.source}: {key}: unknown key(s) {unknown}, allowed {sorted(allowed)}")
        for name in required:
            if name not in value:
                raise CalibrationError(f"{self.source}: {key}.{name}: missing (required)")
        return value

    def number(self, value: Any, key: str, positive: bool = False, non_negative: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not _finite(value):
            raise self.fail(key, "a finite number", value)
        if positive and value <= 0:
            raise self.fail(key, "a positive number", value)
        if non_negative and value < 0:
            raise self.fail(key, "a non-negative number", value)
        return float(value)

    def integer(self, value: Any, key: str) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise self.fail(key, "a positive integer", value)
        return value

    def vector(self, value: Any, key: str, n: int, scalar_ok: bool = False, non_negative: bool = False) -> np.ndarray:
        what = f"a number or a list of {n} numbers" if scalar_ok else f"a list of {n} numbers"
        if scalar_ok and not isinstance(value, list):
            try:
                return np.full(n, self.number(value, key, non_negative=non_negative))
            except CalibrationError:
                raise self.fail(key, what, value) from None
        if not isinstance(value, list) or len(value) != n:
            raise self.fail(key, what, value)
        try:
            return np.array([self.number(x, key, non_negative=non_negative) for x in value])
        except CalibrationError:
            raise self.fail(key, what + (" (non-negative)" if non_negative else ""), value) from None

    def rotation(self, value: Any, key: str) -> np.ndarray:
        if not isinstance(value, list) or len(value) != 3:
            raise self.fail(key, "a 3x3 rotation matrix (list of 3 rows)", value)
        r = np.array([self.vector(row, f"{key}[{i}]", 3) for i, row in enumerate(value)])
        if not is_proper_rotation(r):
            raise self.fail(key, "a proper rotation (orthonormal, det +1)", value)
        return r


def calibration_from_yaml(doc: Any, source: str = "dataset.yaml") -> Calibration:
    """Calibration from a parsed ``dataset.yaml``; ``format``, ``name``, ``description`` are not checked here."""
    y = YamlReader(source)
    top = y.mapping(doc, "(top level)", _TOP_KEYS, required=("imu",))
    imu = y.mapping(top["imu"], "imu", {"rate_hz", "R_BI", "gravity", "noise"}, required=("rate_hz", "noise"))
    noise = y.mapping(imu["noise"], "imu.noise", set(_NOISE_KEYS), required=_NOISE_KEYS)
    imu_cal = ImuCalibration(
        rate_hz=y.number(imu["rate_hz"], "imu.rate_hz", positive=True),
        noise=ImuNoise(*(y.vector(noise[k], f"imu.noise.{k}", 3, scalar_ok=True, non_negative=True)
                         for k in _NOISE_KEYS)),
        R_BI=y.rotation(imu["R_BI"], "imu.R_BI") if "R_BI" in imu else np.eye(3),
        gravity=y.number(imu.get("gravity", STANDARD_GRAVITY), "imu.gravity", positive=True),
    )

    gps = y.mapping(top.get("gps"), "gps", {"lever_arm_b", "origin", "time_offset_s"})
    origin = None
    if gps.get("origin") is not None:
        o = y.mapping(gps["origin"], "gps.origin", {"lat", "lon", "alt"}, required=("lat", "lon", "alt"))
        lat, lon, alt = (y.number(o[k], f"gps.origin.{k}") for k in ("lat", "lon", "alt"))
        if abs(lat) > 90.0 or abs(lon) > 180.0:
            raise y.fail("gps.origin", "lat in [-90, 90] and lon in [-180, 180] degrees", o)
        origin = (lat, lon, alt)
    gps_cal = GpsCalibration(y.vector(gps.get("lever_arm_b", [0, 0, 0]), "gps.lever_arm_b", 3), origin,
                             y.number(gps.get("time_offset_s", 0.0), "gps.time_offset_s"))

    truth = y.mapping(top.get("truth"), "truth", {"point_b"})
    init = y.mapping(top.get("init"), "init", {"heading_deg", "heading_sigma_deg", "gyro_bias_sigma_deg_s"})
    heading = init.get("heading_deg")
    heading_sigma = init.get("heading_sigma_deg")
    bias_sigma = init.get("gyro_bias_sigma_deg_s")
    return Calibration(
        imu=imu_cal,
        gps=gps_cal,
        camera=_camera_from_yaml(y, top["camera"]) if top.get("camera") is not None else None,
        initial_heading_rad=None if heading is None else math.radians(y.number(heading, "init.heading_deg")),
        initial_heading_sigma_rad=None
        if heading_sigma is None
        else math.radians(y.number(heading_sigma, "init.heading_sigma_deg", positive=True)),
        initial_gyro_bias_sigma=None
        if bias_sigma is None
        else math.radians(y.number(bias_sigma, "init.gyro_bias_sigma_deg_s", positive=True)),
        truth_point_b=y.vector(truth.get("point_b", [0, 0, 0]), "truth.point_b", 3),
    )


def _camera_from_yaml(y: YamlReader, value: Any) -> CameraCalibration:
    cam = y.mapping(value, "camera", _CAMERA_KEYS, required=("width", "height", "fx", "fy", "cx", "cy"))
    extra = {}
    model = cam.get("model", "radtan")
    if model not in CAMERA_MODELS:
        raise y.fail("camera.model", f"one of {sorted(CAMERA_MODELS)}", model)
    extra["model"] = model
    if "distortion" in cam:
        extra["distortion"] = y.vector(cam["distortion"], "camera.distortion", CAMERA_MODELS[model])
    if "R_BC" in cam:
        extra["R_BC"] = y.rotation(cam["R_BC"], "camera.R_BC")
    if "t_BC" in cam:
        extra["t_BC"] = y.vector(cam["t_BC"], "camera.t_BC", 3)
    if "rate_hz" in cam:
        extra["rate_hz"] = y.number(cam["rate_hz"], "camera.rate_hz", positive=True)
    if "time_offset_s" in cam:
        extra["time_offset_s"] = y.number(cam["time_offset_s"], "camera.time_offset_s")
    return CameraCalibration(
        width=y.integer(cam["width"], "camera.width"),
        height=y.integer(cam["height"], "camera.height"),
        **{k: y.number(cam[k], f"camera.{k}", positive=k in ("fx", "fy")) for k in ("fx", "fy", "cx", "cy")},
        **extra,
    )


def _floats(a: np.ndarray) -> list:
    """Plain Python floats (nested lists) so YAML writes them exactly and without numpy tags."""
    return (np.asarray(a, dtype=float) + 0.0).tolist()


def _scalar_or_list(v: np.ndarray) -> float | list:
    return float(v[0]) if np.all(v == v[0]) else _floats(v)


def calibration_to_yaml(cal: Calibration) -> dict:
    """The ``imu``, ``gps``, ``truth``, ``init`` and ``camera`` sections of ``dataset.yaml``."""
    noise = cal.imu.noise
    origin = cal.gps.origin_lla
    camera = cal.camera
    return {
        "imu": {
            "rate_hz": float(cal.imu.rate_hz),
            "R_BI": _floats(cal.imu.R_BI),
            "gravity": float(cal.imu.gravity),
            "noise": {k: _scalar_or_list(getattr(noise, k)) for k in _NOISE_KEYS},
        },
        "gps": {
            "lever_arm_b": _floats(cal.gps.lever_arm_b),
            "origin": None if origin is None else dict(zip(("lat", "lon", "alt"), map(float, origin))),
            **({"time_offset_s": float(cal.gps.time_offset_s)} if cal.gps.time_offset_s else {}),
        },
        "truth": {"point_b": _floats(cal.truth_point_b)},
        "init": {
            "heading_deg": None if cal.initial_heading_rad is None else math.degrees(cal.initial_heading_rad),
            "heading_sigma_deg": None
            if cal.initial_heading_sigma_rad is None
            else math.degrees(cal.initial_heading_sigma_rad),
            **({"gyro_bias_sigma_deg_s": math.degrees(cal.initial_gyro_bias_sigma)}
               if cal.initial_gyro_bias_sigma is not None else {}),
        },
        "camera": None if camera is None else {
            "width": int(camera.width), "height": int(camera.height),
            "fx": float(camera.fx), "fy": float(camera.fy), "cx": float(camera.cx), "cy": float(camera.cy),
            **({"model": camera.model} if camera.model != "radtan" else {}),
            "distortion": _floats(camera.distortion), "R_BC": _floats(camera.R_BC), "t_BC": _floats(camera.t_BC),
            "rate_hz": float(camera.rate_hz), "time_offset_s": float(camera.time_offset_s),
        },
    }
