"""What each autopilot does with an ODOMETRY message, as its receiving code states it (paraphrased;
docs/mavlink.md names the files). Tests apply these to messages received by real pymavlink peers."""

from __future__ import annotations

import math

from vtolpose.service.outputs.mavlink_output import mavutil

mav = mavutil.mavlink
EV_ESTIMATORS = (mav.MAV_ESTIMATOR_TYPE_UNKNOWN, mav.MAV_ESTIMATOR_TYPE_NAIVE, mav.MAV_ESTIMATOR_TYPE_VISION,
                 mav.MAV_ESTIMATOR_TYPE_VIO)
PX4_POSE_FRAMES = (mav.MAV_FRAME_LOCAL_NED, mav.MAV_FRAME_LOCAL_FRD, mav.MAV_FRAME_LOCAL_ENU, mav.MAV_FRAME_LOCAL_FLU)
PX4_VELOCITY_FRAMES = PX4_POSE_FRAMES + (mav.MAV_FRAME_BODY_FRD,)
DIAGONALS = ((0, 6, 11), (15, 18, 20))  # x y z, roll pitch yaw in the 21-value upper triangle


def finite(values) -> bool:
    return all(math.isfinite(v) for v in values)


def px4_fused_parts(msg, ev_qmin: int = 0) -> set[str]:
    """The parts of ``msg`` PX4's EKF2 would fuse with EKF2_EV_QMIN = ``ev_qmin`` (default 0).

    mavlink_receiver handle_message_odometry: estimator types UNKNOWN/NAIVE/VISION/VIO go to the
    visual odometry topic; position is taken when x, y, z are all finite and the frame is a local one;
    attitude when q is finite. EKF2 UpdateExtVisionSample: velocity and position only when all three
    components are finite and the frame is known; the quaternion only when finite, non-zero, no element
    above 1 and of unit norm. The EV control logic: quality counts only when EKF2_EV_QMIN > 0, and then
    must be at least that.
    """
    if msg.estimator_type not in EV_ESTIMATORS:
        return set()
    if ev_qmin > 0 and msg.quality < ev_qmin:
        return set()
    parts = set()
    if finite((msg.x, msg.y, msg.z)) and msg.frame_id in PX4_POSE_FRAMES:
        parts.add("position")
    q = msg.q
    norm = math.sqrt(sum(v * v for v in q)) if finite(q) else math.nan
    if finite(q) and any(abs(v) > 0 for v in q) and all(abs(v) <= 1 + 1e-5 for v in q) and abs(1 - norm) <= 1e-5:
        parts.add("attitude")
    if finite((msg.vx, msg.vy, msg.vz)) and msg.child_frame_id in PX4_VELOCITY_FRAMES:
        parts.add("velocity")
    return parts


def px4_variances_consistent(msg) -> bool:
    """PX4 reads the diagonal triples one element at a time and uses a triple only when all three are
    finite (else its EKF2_EV*_NOISE parameters): a triple must be all finite and non-negative, or all NaN."""
    for cov in (msg.pose_covariance, msg.velocity_covariance):
        for triple in DIAGONALS:
            values = [cov[i] for i in triple]
            if not (all(math.isnan(v) for v in values) or (finite(values) and min(values) >= 0)):
                return False
    return True


def ardupilot_fuses(msg, qual_min: int = 0) -> bool:
    """GCS_MAVLINK::handle_odometry: only frame_id MAV_FRAME_LOCAL_FRD with child MAV_FRAME_BODY_FRD;
    AP_VisualOdom_MAV::handle_pose_estimate: only when quality >= VISO_QUAL_MIN (default 0); EKF3
    writeExtNavData: a position with NaN is dropped."""
    if msg.frame_id != mav.MAV_FRAME_LOCAL_FRD or msg.child_frame_id != mav.MAV_FRAME_BODY_FRD:
        return False
    return msg.quality >= qual_min and finite((msg.x, msg.y, msg.z))


def ardupilot_errors_known(msg) -> bool:
    """handle_odometry takes posErr/angErr from elements 0, 6, 11 and 15, 18, 20 unless element 0 is NaN:
    when element 0 is a number the others must be numbers too."""
    cov = msg.pose_covariance
    return math.isnan(cov[0]) or finite([cov[i] for triple in DIAGONALS for i in triple])


ARDUPILOT_MIN_INTERVAL_US = 20_000  # NavEKF3 writeExtNavData: extNavIntervalMin_ms
