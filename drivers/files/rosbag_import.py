"""Import a ROS 2 bag (rosbag2 folder, sqlite3 or MCAP storage, or a bare ``.mcap``) into a dataset.

Read with ``rosbags``, whose readers take the message definitions from the bag itself. Topics:

- IMU, ``sensor_msgs/Imu``: rates and specific force written as they are, in the IMU's own axes;
  ``R_BI`` comes from ``--calibration``, else the IMU frame is taken to be ``base_link`` (REP 103
  FLU), so ``R_BI`` turns FLU into our body FRD;
- GPS, ``sensor_msgs/NavSatFix``: WGS84 rows; σ_h from the mean of the east and north variances,
  σ_v from the up variance (or ``gps_sigma`` when the covariance type is UNKNOWN); fixes with
  status NO_FIX are skipped and counted;
- camera, ``sensor_msgs/Image`` (mono8/8UC1, mono16, rgb8, bgr8, rgba8, bgra8) or
  ``sensor_msgs/CompressedImage``: grey PNG frames (needs a calibration with a camera);
- truth, ``geometry_msgs/PoseStamped`` or ``nav_msgs/Odometry``: the pose of the body in an ENU
  world (REP 103/105) turned into our NED/FRD; velocity from the odometry's twist, or from the
  positions' differences for a PoseStamped.

Times are the messages' header stamps (the sensor's clock), not the bag's receive times; rows
are sorted by them and a repeated stamp is skipped and counted. Without ``--calibration`` the IMU
noise comes from the messages' covariances (a per-sample variance σ² at rate f is a density
σ/√f), which must then be given.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Iterator

import cv2
import numpy as np
from rosbags.highlevel import AnyReader

from vtolpose.drivers.files.calibration_yaml import calibration_from_yaml, load_yaml_file
from vtolpose.drivers.files.csvio import NS_PER_S, write_numeric_csv
from vtolpose.drivers.files.dataset import (
    GPS_CSV, GPS_HEADER_WGS84, GPS_SENSOR, GPS_WGS84_FORMATS, GT_CSV, LEICA_CSV, DatasetWriter, ImuSeries, TruthSeries,
    gps_sensor_yaml,
)
from vtolpose.estimator.core.calibration import Calibration, ImuCalibration, ImuNoise
from vtolpose.estimator.core.frames import R_FLU_FRD, flu_to_frd, pose_enu_flu_to_ned_frd
from vtolpose.estimator.core.rotation import quat_to_rot

log = logging.getLogger(__name__)

IMU_TYPES = ("sensor_msgs/msg/Imu",)
GPS_TYPES = ("sensor_msgs/msg/NavSatFix",)
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
TRUTH_TYPES = ("geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry")
NO_FIX, COVARIANCE_UNKNOWN = -1, 0
_COLOUR = {"rgb8": cv2.COLOR_RGB2GRAY, "bgr8": cv2.COLOR_BGR2GRAY, "rgba8": cv2.COLOR_RGBA2GRAY, "bgra8": cv2.COLOR_BGRA2GRAY}
_CHANNELS = {"mono8": 1, "8UC1": 1, "mono16": 2, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}


class BagImportError(ValueError):
    """The bag cannot be imported as asked; the message names the topic and what is wrong."""


def _t_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * NS_PER_S + int(msg.header.stamp.nanosec)


def _ordered(t_ns: list[int], rows: list, what: str, skipped: dict[str, int]) -> tuple[np.ndarray, list]:
    """Rows sorted by stamp; a stamp seen before is skipped and counted under ``what``."""
    order = sorted(range(len(t_ns)), key=t_ns.__getitem__)
    keep = [i for k, i in enumerate(order) if k == 0 or t_ns[i] != t_ns[order[k - 1]]]
    if len(keep) < len(order):
        skipped[what] = skipped.get(what, 0) + len(order) - len(keep)
    return np.array([t_ns[i] for i in keep], dtype=np.int64), [rows[i] for i in keep]


class BagTopics:
    """The bag, opened, with the requested topics checked against what it holds."""

    def __init__(self, reader: AnyReader) -> None:
        self.reader = reader
        self.types = {c.topic: c.msgtype for c in reader.connections}

    def check(self, topic: str, allowed: tuple[str, ...], role: str) -> str:
        if topic not in self.types:
            have = ", ".join(f"{t} ({m})" for t, m in sorted(self.types.items())) or "none"
            raise BagImportError(f"--{role} {topic}: no such topic in the bag; it has {have}")
        if self.types[topic] not in allowed:
            raise BagImportError(f"--{role} {topic}: is {self.types[topic]}, expected {' or '.join(allowed)}")
        return self.types[topic]

    def messages(self, topic: str) -> Iterator[Any]:
        connections = [c for c in self.reader.connections if c.topic == topic]
        for connection, _, raw in self.reader.messages(connections=connections):
            yield self.reader.deserialize(raw, connection.msgtype)


def _vec3(v: Any) -> list[float]:
    return [float(v.x), float(v.y), float(v.z)]


def read_imu(bag: BagTopics, topic: str, skipped: dict[str, int]) -> tuple[ImuSeries, np.ndarray, np.ndarray]:
    """IMU samples in the message axes, and the mean gyro and accel per-sample variances (NaN if not given)."""
    t, rows, var_g, var_a = [], [], [], []
    for msg in bag.messages(topic):
        t.append(_t_ns(msg))
        rows.append(_vec3(msg.angular_velocity) + _vec3(msg.linear_acceleration))
        var_g.append(np.diag(np.asarray(msg.angular_velocity_covariance).reshape(3, 3)))
        var_a.append(np.diag(np.asarray(msg.linear_acceleration_covariance).reshape(3, 3)))
    if len(t) < 2:
        raise BagImportError(f"--imu {topic}: {len(t)} message(s); at least 2 are needed")
    t_ns, rows = _ordered(t, rows, "imu_repeated_stamp", skipped)
    values = np.array(rows)
    return ImuSeries(t_ns, values[:, :3], values[:, 3:]), np.mean(var_g, axis=0), np.mean(var_a, axis=0)


def read_gps(bag: BagTopics, topic: str, gps_sigma: tuple[float, float] | None,
             skipped: dict[str, int]) -> tuple[np.ndarray, np.ndarray]:
    """Fix times and rows ``lat, lon, alt, sigma_h, sigma_v``."""
    t, rows = [], []
    for msg in bag.messages(topic):
        if msg.status.status <= NO_FIX:
            skipped["gps_no_fix"] = skipped.get("gps_no_fix", 0) + 1
            continue
        cov = np.asarray(msg.position_covariance, dtype=float).reshape(3, 3)
        if msg.position_covariance_type == COVARIANCE_UNKNOWN:
            if gps_sigma is None:
                raise BagImportError(f"--gps {topic}: fixes without a covariance (type UNKNOWN); give --fix-sigma H[,V] in metres")
            sigma_h, sigma_v = gps_sigma
        else:
            sigma_h, sigma_v = float(np.sqrt(0.5 * (cov[0, 0] + cov[1, 1]))), float(np.sqrt(cov[2, 2]))
        t.append(_t_ns(msg))
        rows.append([float(msg.latitude), float(msg.longitude), float(msg.altitude), sigma_h, sigma_v])
    if not t:
        raise BagImportError(f"--gps {topic}: no usable fix")
    t_ns, rows = _ordered(t, rows, "gps_repeated_stamp", skipped)
    return t_ns, np.array(rows)


def grey_image(msg: Any, msgtype: str) -> np.ndarray:
    """A ``sensor_msgs`` Image or CompressedImage as a grey uint8 array (ValueError if it cannot be)."""
    if msgtype.endswith("CompressedImage"):
        image = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise ValueError(f"CompressedImage of format {msg.format!r} does not decode")
        return image
    channels = _CHANNELS.get(msg.encoding)
    if channels is None:
        raise ValueError(f"image encoding {msg.encoding!r} (use one of {', '.join(_CHANNELS)})")
    data = np.asarray(msg.data, dtype=np.uint8).reshape(msg.height, msg.step)[:, :msg.width * channels]
    if msg.encoding == "mono16":
        words = data.copy().view(">u2" if msg.is_bigendian else "<u2")
        return (words >> 8).astype(np.uint8)
    image = data.reshape(msg.height, msg.width, channels) if channels > 1 else data
    return cv2.cvtColor(image, _COLOUR[msg.encoding]) if channels > 1 else np.ascontiguousarray(image)


def read_frames(bag: BagTopics, topic: str, msgtype: str, skipped: dict[str, int]) -> Iterator[tuple[int, np.ndarray]]:
    """Frames in bag order, each stamp later than the last (others skipped and counted)."""
    last = None
    for msg in bag.messages(topic):
        t = _t_ns(msg)
        if last is not None and t <= last:
            skipped["image_out_of_order"] = skipped.get("image_out_of_order", 0) + 1
            continue
        try:
            image = grey_image(msg, msgtype)
        except ValueError as exc:
            raise BagImportError(f"--image {topic}: {exc}") from None
        last = t
        yield t, image


def read_truth(bag: BagTopics, topic: str, msgtype: str, skipped: dict[str, int]) -> TruthSeries:
    """The body pose in an ENU world as NED/FRD truth with velocity (the twist, or position differences)."""
    t, rows = [], []
    for msg in bag.messages(topic):
        pose = msg.pose.pose if msgtype.endswith("Odometry") else msg.pose
        o = pose.orientation
        twist = _vec3(msg.twist.twist.linear) if msgtype.endswith("Odometry") else [np.nan] * 3
        t.append(_t_ns(msg))
        rows.append(_vec3(pose.position) + [float(o.w), float(o.x), float(o.y), float(o.z)] + twist)
    if len(t) < 2:
        raise BagImportError(f"--truth {topic}: {len(t)} message(s); at least 2 are needed")
    t_ns, rows = _ordered(t, rows, "truth_repeated_stamp", skipped)
    values = np.array(rows)
    p, q = pose_enu_flu_to_ned_frd(values[:, 0:3], values[:, 3:7])
    if msgtype.endswith("Odometry"):  # the twist is in the child (body, FLU) frame
        v = np.einsum("nij,nj->ni", quat_to_rot(q), flu_to_frd(values[:, 7:10]))
    else:
        v = np.gradient(p, t_ns * 1e-9, axis=0)
    return TruthSeries(t_ns, p, q, v)


def default_calibration(imu: ImuSeries, var_gyro: np.ndarray, var_accel: np.ndarray, topic: str) -> Calibration:
    """A calibration from the bag alone: IMU = base_link (FLU), noise densities from the covariances."""
    rate = float(NS_PER_S / np.median(np.diff(imu.t_ns)))
    if not (np.all(var_gyro > 0.0) and np.all(var_accel > 0.0)):
        raise BagImportError(f"--imu {topic}: the messages carry no rate/acceleration covariance, so the IMU noise "
                             "is unknown; give --calibration FILE (a dataset.yaml-format file with the vehicle's calibration)")
    noise = ImuNoise(np.sqrt(var_gyro / rate), np.zeros(3), np.sqrt(var_accel / rate), np.zeros(3))
    return Calibration(imu=ImuCalibration(rate_hz=rate, noise=noise, R_BI=R_FLU_FRD.T))


def import_rosbag(
    bag_path: str | Path, out: str | Path, imu_topic: str, gps_topic: str, image_topic: str | None = None,
    truth_topic: str | None = None, calibration_file: str | Path | None = None,
    gps_sigma: tuple[float, float] | None = None, overwrite: bool = False,
) -> dict[str, Any]:
    """Write the bag's topics into dataset ``out`` (see the module docstring); returns a summary."""
    bag_path, out = Path(bag_path), Path(out)
    if (out / "dataset.yaml").exists() and not overwrite:
        raise FileExistsError(f"{out}: already holds a dataset (dataset.yaml); pass --force to replace it")
    calibration = None
    if calibration_file is not None:
        if not Path(calibration_file).is_file():
            raise FileNotFoundError(f"--calibration {calibration_file}: file not found")
        calibration = calibration_from_yaml(load_yaml_file(Path(calibration_file)), str(calibration_file))
    if image_topic is not None and (calibration is None or calibration.camera is None):
        raise BagImportError(f"--image {image_topic}: frames need the camera's calibration; give --calibration FILE with a camera section")
    skipped: dict[str, int] = {}
    with AnyReader([bag_path]) as reader:
        bag = BagTopics(reader)
        bag.check(imu_topic, IMU_TYPES, "imu")
        bag.check(gps_topic, GPS_TYPES, "gps")
        image_type = bag.check(image_topic, IMAGE_TYPES, "image") if image_topic else None
        truth_type = bag.check(truth_topic, TRUTH_TYPES, "truth") if truth_topic else None
        imu, var_g, var_a = read_imu(bag, imu_topic, skipped)
        gps_t, gps_rows = read_gps(bag, gps_topic, gps_sigma, skipped)
        truth = read_truth(bag, truth_topic, truth_type, skipped) if truth_topic else None
        if calibration is None:
            calibration = default_calibration(imu, var_g, var_a, imu_topic)
        writer = DatasetWriter(out)
        for stale in (GPS_CSV, GPS_SENSOR, GT_CSV, LEICA_CSV):
            (out / stale).unlink(missing_ok=True)
        source = "the calibration file " + str(calibration_file) if calibration_file else "the bag (IMU = base_link, FLU)"
        writer.write_calibration(calibration, bag_path.stem, f"ROS 2 bag {bag_path.name} imported by vtolpose; "
                                 f"calibration from {source}")
        writer.write_imu(imu)
        write_numeric_csv(out / GPS_CSV, GPS_HEADER_WGS84, gps_t, gps_rows, GPS_WGS84_FORMATS)
        (out / GPS_SENSOR).write_text(gps_sensor_yaml("WGS84"), encoding="utf-8", newline="\n")
        if truth is not None:
            writer.write_truth(truth)
        frames = writer.write_camera_frames(read_frames(bag, image_topic, image_type, skipped)) if image_topic else 0
    return {
        "out": str(out), "imu_samples": int(imu.t_ns.size),
        "imu_rate_hz_measured": float(NS_PER_S / np.median(np.diff(imu.t_ns))),
        "gps_fixes": int(gps_t.size), "camera_frames": frames, "truth_poses": 0 if truth is None else int(truth.t_ns.size),
        "duration_s": float((imu.t_ns[-1] - imu.t_ns[0]) * 1e-9), "skipped": skipped,
    }
