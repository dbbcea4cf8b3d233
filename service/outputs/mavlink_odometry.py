"""ODOMETRY (id 331) fields from a pose, as each autopilot's receiving code reads them.

Position NED, ``q`` body→frame, velocity and angular rate in the body (FRD) frame, 21-value
upper-triangle covariances, the estimator's ``reset_counter``, ``MAV_ESTIMATOR_TYPE_VIO``.
What differs per autopilot (docs/mavlink.md has the sources):

- ``frame_id``: ArduPilot takes ODOMETRY only with ``MAV_FRAME_LOCAL_FRD`` (its MAVLink backend feeds
  the position to EKF3 unrotated); PX4 gets ``MAV_FRAME_LOCAL_NED`` while the heading is
  north-referenced, else ``MAV_FRAME_LOCAL_FRD``; generic receivers ``MAV_FRAME_LOCAL_NED``. The frame
  (and ArduPilot's yaw continuity) is :mod:`.mavlink_frame`'s.
- A pose that must not be used (:func:`pose_problem`) always has ``quality = -1`` ("failed"). ArduPilot
  drops it below ``VISO_QUAL_MIN`` (default 0). PX4 ignores the quality unless ``EKF2_EV_QMIN`` > 0,
  so the PX4 profile also sends position, attitude and velocity as NaN: EKF2 takes no part of an
  ODOMETRY whose values are not finite, whatever its parameters.
- Unknown covariance is NaN in all 21 places (the definition's invalid value): PX4 reads the diagonal
  elements one by one and falls back to its noise parameters unless a whole triple is finite;
  ArduPilot looks at the first element only.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from vtolpose.drivers.links.mavlink_wire import mavutil
from vtolpose.estimator import OutputPose, rot_of
from vtolpose.service.runtime.status import pose_problem, usable_pose_quality

__all__ = ["ODOMETRY_CRC_EXTRA", "ODOMETRY_ID", "PROFILES", "Profile", "euler_jacobian", "odometry_covariances",
           "odometry_fields", "odometry_payload", "odometry_quality", "upper_triangle"]

mav = mavutil.mavlink
_TRIU = np.triu_indices(6)  # row-major upper-right triangle: 21 indices
_TRIU_FLAT = _TRIU[0] * 6 + _TRIU[1]  # the same in a flat 6 × 6
NAN21 = [math.nan] * 21


@dataclass(frozen=True, slots=True)
class Profile:
    name: str
    frame_id: int
    nan_when_unusable: bool  # send the values of an unusable pose as NaN (PX4 ignores quality by default)
    min_spacing_ns: int = 0  # never two ODOMETRY closer than this (ArduPilot's EKF3 drops them)


PROFILES = {  # frame_id: the north-referenced one (PX4's is FRD while the heading is not placed)
    "px4": Profile("px4", mav.MAV_FRAME_LOCAL_NED, True),
    "ardupilot": Profile("ardupilot", mav.MAV_FRAME_LOCAL_FRD, False, min_spacing_ns=21_000_000),
    "generic": Profile("generic", mav.MAV_FRAME_LOCAL_NED, False),
}


def odometry_quality(pose: OutputPose) -> int:
    """-1 when the pose must not be used (:func:`pose_problem`), else 1-100 (the status's quality)."""
    return -1 if pose_problem(pose) is not None else usable_pose_quality(pose)


def _euler_rows(w: float, x: float, y: float, z: float) -> tuple[tuple[float, float, float], ...]:
    """:func:`euler_jacobian`'s rows on plain floats."""
    sp = min(max(2.0 * (w * y - z * x), -1.0), 1.0)
    cp = max(math.sqrt(1.0 - sp * sp), 1e-6)
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    cy, sy = math.cos(yaw), math.sin(yaw)
    return (cy / cp, sy / cp, 0.0), (-sy, cy, 0.0), (sp * cy / cp, sp * sy / cp, 1.0)


def euler_jacobian(q: np.ndarray) -> np.ndarray:
    """d(roll, pitch, yaw) / dθ for a world-frame attitude error θ (``R_true = Exp(θ) R``).

    With R = Rz(ψ) Ry(θ) Rx(φ), a world-frame rotation increment is
    ``δθ = [Rz Ry e_x | Rz e_y | e_z] · (δφ, δθ, δψ)``; this is that matrix's inverse, in closed
    form. It is singular at ±90° pitch, which a helicopter's estimator never reports:
    cos(pitch) is floored.
    """
    return np.array(_euler_rows(*np.asarray(q, dtype=float).tolist()))


def _flat9(rows: np.ndarray) -> np.ndarray:
    """Flat indices into a 9 × 9 of the ``rows`` × ``rows`` block."""
    return (rows[:, None] * 9 + rows[None, :]).ravel()


# The [δp, δθ] and the [δv, δθ] blocks of a flat 9 × 9, stacked: both covariance products in one.
_BLOCKS_FLAT = np.concatenate([_flat9(np.r_[0:3, 6:9]), _flat9(np.r_[3:9])]).reshape(2, 6, 6)
# Out of the stacked (2, 6, 6) products: the pose's 21-value triangle, then the body velocity's 3 × 3 triangle.
_TRIANGLES_FLAT = np.concatenate([_TRIU_FLAT, 36 + np.array([0, 1, 2, 7, 8, 14])])


# J of both products, stacked (2, 6, 6): what does not depend on the pose, and where the rest goes.
_J_CONSTANT = np.zeros((2, 6, 6))
_J_CONSTANT[0, [0, 1, 2, 5], [0, 1, 2, 5]] = 1.0
# The Euler rows 3-5, columns 3-4; then the velocity's rows 0-2, and again in its rows 3-5: those are not used (the
# body rates are filled in after), but zeros there would turn an infinite variance into 0 × ∞ (a warning).
_J_VARIABLE = np.array([21, 22, 27, 28, 33, 34] + list(range(36, 72)))


def _covariance_products(pose: OutputPose, q: list[float], rot: Any, v: list[float]) -> np.ndarray:
    """``J C Jᵀ`` for the pose (0) and the body velocity (1), as one stacked (2, 6, 6) product.

    Pose: the estimator's covariance is over ``[δp (NED), δθ (world-frame rotation)]``; MAVLink's
    states are ``x, y, z, roll, pitch, yaw``, so the attitude block is mapped through the Euler
    Jacobian (first order; at level attitude it is the identity, and yaw's variance is exact).
    Velocity: body-frame velocity ``v_B = Rᵀ v`` depends on the world velocity error and on the
    attitude error (``δv_B = Rᵀ δv + Rᵀ [v]× δθ``); only rows 0-2 of that product count (the body rates
    are apart, see :func:`odometry_covariances`). J is built from plain floats: this runs for every pose sent.
    """
    (e00, e01, _), (e10, e11, _), (e20, e21, _) = _euler_rows(*q)
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = rot
    vx, vy, vz = v
    # Rᵀ and Rᵀ [v]×, row by row (row i of Rᵀ is column i of R).
    velocity = [r00, r10, r20, r10 * vz - r20 * vy, r20 * vx - r00 * vz, r00 * vy - r10 * vx,
                r01, r11, r21, r11 * vz - r21 * vy, r21 * vx - r01 * vz, r01 * vy - r11 * vx,
                r02, r12, r22, r12 * vz - r22 * vy, r22 * vx - r02 * vz, r02 * vy - r12 * vx]
    j = _J_CONSTANT.copy()
    j.put(_J_VARIABLE, [e00, e01, e10, e11, e20, e21] + velocity + velocity)
    return j @ pose.cov9.take(_BLOCKS_FLAT) @ j.transpose(0, 2, 1)


def odometry_covariances(pose: OutputPose, r: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """ODOMETRY's two 6 × 6 covariances from the estimator's (:func:`_covariance_products`): the pose's,
    and the body velocity's with the body rates, the bias-corrected gyro, uncorrelated with the
    velocity, with the gyro noise plus the bias variance."""
    q = pose.q.tolist()
    products = _covariance_products(pose, q, rot_of(*q) if r is None else r.tolist(), pose.v.tolist())
    vel_cov = np.zeros((6, 6))
    vel_cov[0:3, 0:3] = products[1, 0:3, 0:3]
    vel_cov[3, 3], vel_cov[4, 4], vel_cov[5, 5] = pose.omega_var.tolist()
    return products[0], vel_cov


def _known(values: list[float]) -> list[float]:
    """``values``, or all NaN (unknown) when any is not finite."""
    if not math.isfinite(sum(values)):  # a NaN or an infinity anywhere (or values so large they overflow)
        return list(NAN21) if not all(map(math.isfinite, values)) else values
    return values


def upper_triangle(cov: np.ndarray) -> list[float]:
    """The 21 values of the upper-right triangle, row-major; all NaN when any is not finite (unknown)."""
    return _known(cov.take(_TRIU_FLAT).tolist())


def odometry_fields(pose: OutputPose, profile: Profile = PROFILES["generic"], frame_id: int | None = None,
                    reset_counter: int | None = None) -> dict[str, Any]:
    """Keyword arguments of ``odometry_encode`` for ``pose`` as ``profile``'s autopilot reads them;
    ``frame_id`` and ``reset_counter``, when given, as :class:`~.mavlink_frame.PublishedFrame` says.

    It runs for every pose sent, so it works on plain floats around one numpy product."""
    quality = odometry_quality(pose)
    fields: dict[str, Any] = dict(
        time_usec=pose.t_ns // 1000,
        frame_id=profile.frame_id if frame_id is None else frame_id,
        child_frame_id=mav.MAV_FRAME_BODY_FRD,
        reset_counter=(pose.reset_counter if reset_counter is None else reset_counter) % 256,
        estimator_type=mav.MAV_ESTIMATOR_TYPE_VIO,
        quality=quality,
    )
    if quality < 0 and profile.nan_when_unusable:
        nan = math.nan
        fields.update(x=nan, y=nan, z=nan, q=[nan] * 4, vx=nan, vy=nan, vz=nan, rollspeed=nan, pitchspeed=nan,
                      yawspeed=nan, pose_covariance=list(NAN21), velocity_covariance=list(NAN21))
        return fields
    q = pose.q.tolist()
    rot = rot_of(*q)
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = rot
    v = pose.v.tolist()
    vx, vy, vz = v
    x, y, z = pose.p.tolist()
    rollspeed, pitchspeed, yawspeed = pose.omega_b.tolist()
    triangles = _covariance_products(pose, q, rot, v).take(_TRIANGLES_FLAT).tolist()
    v00, v01, v02, v11, v12, v22 = triangles[21:]
    w0, w1, w2 = pose.omega_var.tolist()
    fields.update(
        x=x, y=y, z=z, q=q, rollspeed=rollspeed, pitchspeed=pitchspeed, yawspeed=yawspeed,
        vx=r00 * vx + r10 * vy + r20 * vz, vy=r01 * vx + r11 * vy + r21 * vz, vz=r02 * vx + r12 * vy + r22 * vz,  # Rᵀ v
        pose_covariance=_known(triangles[:21]),
        velocity_covariance=_known([v00, v01, v02, 0.0, 0.0, 0.0, v11, v12, 0.0, 0.0, 0.0, v22, 0.0, 0.0, 0.0,
                                    w0, 0.0, 0.0, w1, 0.0, w2]),
    )
    return fields

ODOMETRY_ID = mav.MAVLINK_MSG_ID_ODOMETRY
ODOMETRY_CRC_EXTRA = mav.MAVLink_odometry_message.crc_extra  # 91: the checksum's seed from the message's definition
# The wire order (fields by size, largest first; the MAVLink 2 extensions last), all little-endian.
_ODOMETRY = struct.Struct("<Q3f4f6f21f21f4Bb")


def odometry_payload(f: dict[str, Any]) -> bytes:
    """ODOMETRY's full 233-byte payload from :func:`odometry_fields` (the frame cuts its trailing zeros),
    byte for byte what pymavlink's ``MAVLink_odometry_message(**f)`` packs."""
    return _ODOMETRY.pack(f["time_usec"], f["x"], f["y"], f["z"], *f["q"], f["vx"], f["vy"], f["vz"], f["rollspeed"],
                          f["pitchspeed"], f["yawspeed"], *f["pose_covariance"], *f["velocity_covariance"], f["frame_id"],
                          f["child_frame_id"], f["reset_counter"], f["estimator_type"], f["quality"])
