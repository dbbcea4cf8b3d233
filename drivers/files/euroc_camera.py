"""EuRoC ``cam0``: the camera's calibration in our frames, and its images into a dataset.

EuRoC's ``sensor.yaml`` gives a pinhole camera (``intrinsics: [fu, fv, cu, cv]``,
``resolution: [width, height]``), radial-tangential distortion ``[k1, k2, p1, p2]`` (or Kalibr's
``equidistant`` fisheye, ``[k1, k2, k3, k4]``) and
``T_BS``, the camera's pose on EuRoC's body B. Our ``R_BC`` maps camera axes (x right, y down,
z forward: the same convention) into body FRD, and ``t_BC`` is the optical centre in FRD:

    R_BC = R_BI · R_BI_eurocᵀ · R_BS_cam,    t_BC = R_BI · R_BI_eurocᵀ · (t_BS_cam − t_BI_euroc)

The VI-sensor stamps images and IMU on one clock, so the time offset is zero.
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import numpy as np

from vtolpose.drivers.files.calibration_yaml import YamlReader, load_yaml_file
from vtolpose.drivers.files.dataset import CAM_CSV, CAM_DIR
from vtolpose.drivers.files.euroc_truth import Frames, read_mount
from vtolpose.drivers.files.frames_csv import image_kind, read_frame_index, write_frame_index
from vtolpose.estimator.core.calibration import CameraCalibration

log = logging.getLogger(__name__)

RADTAN_NAMES = ("radial-tangential", "radtan")
EQUIDISTANT_NAMES = ("equidistant",)  # Kalibr's name for the Kannala–Brandt fisheye (cv2.fisheye)
IMPORTED_SUFFIX = {"png": ".png", "jpeg": ".jpg"}  # formats kept as they are, by what their header says


def camera_calibration(sensor_yaml: Path, frames: Frames) -> CameraCalibration:
    """Our camera calibration from a EuRoC camera ``sensor.yaml``; errors name the file and the key."""
    doc = load_yaml_file(sensor_yaml)
    y = YamlReader(str(sensor_yaml))
    if not isinstance(doc, dict):
        raise y.fail("(top level)", "a mapping", doc)
    for key in ("intrinsics", "resolution", "distortion_coefficients"):
        if key not in doc:
            raise ValueError(f"{sensor_yaml}: {key}: missing (required)")
    model = doc.get("camera_model", "pinhole")
    if model != "pinhole":
        raise y.fail("camera_model", "pinhole", model)
    distortion_model = doc.get("distortion_model", "radial-tangential")
    if distortion_model not in RADTAN_NAMES + EQUIDISTANT_NAMES:
        raise y.fail("distortion_model", f"one of {list(RADTAN_NAMES + EQUIDISTANT_NAMES)} (the models this program uses)",
                     distortion_model)
    fisheye = distortion_model in EQUIDISTANT_NAMES
    fu, fv, cu, cv = y.vector(doc["intrinsics"], "intrinsics", 4)
    width, height = (y.integer(v, "resolution") for v in _pair(y, doc["resolution"]))
    coeffs = doc["distortion_coefficients"]
    if fisheye:
        k = y.vector(coeffs, "distortion_coefficients", 4)
    else:
        n = len(coeffs) if isinstance(coeffs, list) and len(coeffs) in (4, 5) else 4
        k = np.zeros(5)
        k[:n] = y.vector(coeffs, "distortion_coefficients", n)
    mount = read_mount(sensor_yaml)
    to_body = frames.R_BI @ frames.imu.R_BS.T
    return CameraCalibration(
        width=width, height=height, fx=fu, fy=fv, cx=cu, cy=cv, distortion=k,
        R_BC=to_body @ mount.R_BS, t_BC=to_body @ (mount.t_BS - frames.imu.t_BS),
        rate_hz=y.number(doc.get("rate_hz", 20.0), "rate_hz", positive=True), time_offset_s=0.0,
        model="equidistant" if fisheye else "radtan",
    )


def _pair(y: YamlReader, value: object) -> list:
    if not isinstance(value, list) or len(value) != 2:
        raise y.fail("resolution", "[width, height]", value)
    return value


def copy_frames(cam_dir: Path, out: Path) -> tuple[int, int]:
    """The images listed in ``cam_dir/data.csv`` into dataset ``out`` as ``<t_ns>.png`` or ``<t_ns>.jpg``
    (hard-linked where the file system allows, else copied: the bytes stay the recording's, a JPEG is not
    re-encoded). Any resolution; a file that is no PNG or JPEG by its header is skipped with a warning
    naming it and what it is. Returns (frames, skipped)."""
    frames, skipped = read_frame_index(cam_dir / "data.csv", cam_dir / "data")
    target = out / CAM_DIR
    if target.exists():
        shutil.rmtree(target)
    target.mkdir(parents=True)
    times, suffixes = [], []
    for t_ns, path in frames:
        kind = image_kind(path) if path.is_file() else None
        if kind not in IMPORTED_SUFFIX:
            why = "missing" if not path.exists() else "not a file" if not path.is_file() else \
                f"not a PNG or JPEG by its header ({kind or 'unknown format'})"
            log.warning("%s: %s, frame skipped", path, why)
            skipped += 1
            continue
        dest = target / f"{t_ns}{IMPORTED_SUFFIX[kind]}"
        try:
            os.link(path, dest)
        except OSError:
            shutil.copyfile(path, dest)
        times.append(t_ns)
        suffixes.append(dest.suffix)
    write_frame_index(out / CAM_CSV, times, suffixes)
    return len(times), skipped
