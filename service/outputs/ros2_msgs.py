"""ROS 2 messages made from vtolpose's poses and samples, serialised to CDR by ``rosbags``.

The one place that applies ROS conventions to our data (REP 103/105): the world frame is ENU
(``map``, optionally ``odom`` under it), the body ``base_link`` is FLU, and the conversion from
the estimator's NED/FRD happens here, through :mod:`vtolpose.estimator.core.frames`, and nowhere
else. The same builders serve the Zenoh bridge (``ros2.py``) and the MCAP recording (``mcap.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from rosbags.typesys import Stores, get_typestore

from vtolpose.estimator import (
    body_covariance_frd_to_flu, frd_to_flu, ImuSample, OutputPose, pose_covariance_ned_to_enu,
    pose_ned_frd_to_enu_flu, quat_to_rot,
)
from vtolpose.service.outputs.mavlink_output import odometry_covariances

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)  # message layouts (and RIHS01 hashes) of the current LTS
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
IMU = "sensor_msgs/msg/Imu"
NAV_SAT_FIX = "sensor_msgs/msg/NavSatFix"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
_T = TYPESTORE.types
_NS_PER_S = 1_000_000_000


@dataclass(frozen=True, slots=True)
class RosFrames:
    """Frame ids (REP 105): ``world`` ENU (``map``), ``odom`` under it (None: no odom frame), ``body`` FLU."""

    world: str = "map"
    odom: str | None = "odom"
    body: str = "base_link"


def serialize(msg: object, typename: str) -> bytes:
    return bytes(TYPESTORE.serialize_cdr(msg, typename))


def message_definition(typename: str) -> str:
    """The ``ros2msg`` text of a type with its dependencies (an MCAP schema, a bag's connection)."""
    return TYPESTORE.generate_msgdef(typename, ros_version=2)[0]


def type_hash(typename: str) -> str:
    """REP 2016 type hash, ``RIHS01_<sha256>``."""
    return TYPESTORE.hash_rihs01(typename)


def stamp(t_ns: int) -> object:
    """``builtin_interfaces/Time`` from integer nanoseconds (seconds floor, nanoseconds in [0, 1e9))."""
    sec, nanosec = divmod(int(t_ns), _NS_PER_S)
    if not -(2**31) <= sec < 2**31:
        raise ValueError(f"time {t_ns} ns does not fit a ROS 2 stamp (int32 seconds)")
    return _T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def header(t_ns: int, frame_id: str) -> object:
    return _T["std_msgs/msg/Header"](stamp=stamp(t_ns), frame_id=frame_id)


def _vector(v: np.ndarray, kind: str = "geometry_msgs/msg/Vector3") -> object:
    x, y, z = v.tolist()
    return _T[kind](x=x, y=y, z=z)


def _quaternion(q_wxyz: np.ndarray) -> object:
    w, x, y, z = q_wxyz.tolist()
    return _T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)


@dataclass(frozen=True, slots=True)
class RosPose:
    """One estimate in REP 103 terms, converted once for every message made from it."""

    t_ns: int
    p: np.ndarray  # ENU
    q: np.ndarray  # FLU -> ENU, w first
    pose_cov: np.ndarray  # 6 × 6 over [δp, δθ], ENU
    linear: np.ndarray  # body velocity, FLU
    angular: np.ndarray  # body rate, FLU
    twist_cov: np.ndarray  # 6 × 6 over [linear, angular], FLU


def ros_pose(pose: OutputPose, t_ns: int) -> RosPose:
    """The estimate in ENU/FLU.

    Pose covariance: the estimator's ``[δp, δθ]`` turned into ENU (its attitude error is about
    the world axes, as ROS's "fixed axis" rotation covariance is). Twist covariance: the body
    velocity's (``δv_B = Rᵀ δv + Rᵀ [v]× δθ``) and the body rates', as the ODOMETRY output has them,
    turned into FLU.
    """
    p_enu, q_enu = pose_ned_frd_to_enu_flu(pose.p, pose.q)
    _, twist_cov_frd = odometry_covariances(pose)
    v_body = quat_to_rot(pose.q).T @ pose.v
    return RosPose(t_ns, p_enu, q_enu, pose_covariance_ned_to_enu(pose.pose_cov), frd_to_flu(v_body),
                   frd_to_flu(pose.omega_b), body_covariance_frd_to_flu(twist_cov_frd))


def odometry(pose: RosPose, frames: RosFrames) -> object:
    """``nav_msgs/Odometry``: pose of ``body`` in ``world`` (ENU/FLU) and the twist in ``body``."""
    P = _T["geometry_msgs/msg/Pose"]
    return _T[ODOMETRY](
        header=header(pose.t_ns, frames.world), child_frame_id=frames.body,
        pose=_T["geometry_msgs/msg/PoseWithCovariance"](
            pose=P(position=_vector(pose.p, "geometry_msgs/msg/Point"), orientation=_quaternion(pose.q)),
            covariance=pose.pose_cov.reshape(36)),
        twist=_T["geometry_msgs/msg/TwistWithCovariance"](
            twist=_T["geometry_msgs/msg/Twist"](linear=_vector(pose.linear), angular=_vector(pose.angular)),
            covariance=pose.twist_cov.reshape(36)),
    )


_IDENTITY_Q = np.array([1.0, 0.0, 0.0, 0.0])


def _transform(t_ns: int, parent: str, child: str, p: np.ndarray, q_wxyz: np.ndarray) -> object:
    return _T["geometry_msgs/msg/TransformStamped"](
        header=header(t_ns, parent), child_frame_id=child,
        transform=_T["geometry_msgs/msg/Transform"](translation=_vector(p), rotation=_quaternion(q_wxyz)))


def transforms(pose: RosPose, frames: RosFrames) -> object:
    """``tf2_msgs/TFMessage``: ``world → odom`` (identity: one estimator is both the map and the
    odometry source) and ``odom → body`` with the pose; without an odom frame, ``world → body``."""
    parent = frames.odom or frames.world
    items = [_transform(pose.t_ns, parent, frames.body, pose.p, pose.q)]
    if frames.odom is not None:
        items.insert(0, _transform(pose.t_ns, frames.world, frames.odom, np.zeros(3), _IDENTITY_Q))
    return _T[TF_MESSAGE](transforms=items)


_NO_ORIENTATION = np.r_[-1.0, np.zeros(8)]  # sensor_msgs/Imu: covariance[0] = -1 means "no orientation"


def imu(sample: ImuSample, frame_id: str) -> object:
    """``sensor_msgs/Imu`` of one raw sample (rates and specific force), body FRD turned into FLU."""
    return _T[IMU](
        header=header(sample.t_ns, frame_id), orientation=_quaternion(np.array([1.0, 0.0, 0.0, 0.0])),
        orientation_covariance=_NO_ORIENTATION, angular_velocity=_vector(frd_to_flu(sample.gyro)),
        angular_velocity_covariance=np.zeros(9), linear_acceleration=_vector(frd_to_flu(sample.accel)),
        linear_acceleration_covariance=np.zeros(9))


STATUS_FIX, SERVICE_GPS, COVARIANCE_DIAGONAL_KNOWN = 0, 1, 2  # NavSatStatus / NavSatFix constants


def nav_sat_fix(t_ns: int, frame_id: str, lat_deg: float, lon_deg: float, alt_m: float,
                sigma_h: float, sigma_v: float) -> object:
    """``sensor_msgs/NavSatFix`` with a diagonal ENU covariance from the fix's 1-σ errors."""
    return _T[NAV_SAT_FIX](
        header=header(t_ns, frame_id), status=_T["sensor_msgs/msg/NavSatStatus"](status=STATUS_FIX, service=SERVICE_GPS),
        latitude=float(lat_deg), longitude=float(lon_deg), altitude=float(alt_m),
        position_covariance=np.diag([sigma_h**2, sigma_h**2, sigma_v**2]).reshape(9).astype(float),
        position_covariance_type=COVARIANCE_DIAGONAL_KNOWN)


def compressed_image(t_ns: int, frame_id: str, data: bytes, fmt: str) -> object:
    """``sensor_msgs/CompressedImage`` (``fmt``: "png" or "jpeg")."""
    return _T[COMPRESSED_IMAGE](header=header(t_ns, frame_id), format=fmt, data=np.frombuffer(data, dtype=np.uint8))
