"""The frame an autopilot is told the pose is in, and the steps in it an autopilot can take.

The estimator's frame is north-referenced only once its heading is placed (``heading_aligned``: from
GPS, the dataset or the operator). A camera-only filter that never heard a GPS works in a frame of
its own, whose x axis is wherever the heading started (``local_position``). What each receiver is
told (docs/mavlink.md has the sources):

- PX4: ``MAV_FRAME_LOCAL_NED`` only while the heading is north-referenced, else ``MAV_FRAME_LOCAL_FRD``
  (EKF2 then does not take the yaw for a heading). When the frame changes, ``reset_counter`` steps,
  so that EKF2 resets to the pose in its new frame instead of fighting it.
- ArduPilot: always ``MAV_FRAME_LOCAL_FRD`` (the only frame it takes). EKF3 resets only the position
  on a new ``reset_counter`` (``writeExtNavData``); a yaw step (a heading placed after a GPS reset, a
  GPS joining a camera-only frame) reaches it as an innovation its gate refuses. So the published
  frame absorbs every step: it is the estimator's turned about the down axis by ``yaw_offset``, chosen
  at each step so that the published yaw goes on from where it was. ``reset_counter`` steps with the
  frame too, so the position (turned with it) is taken afresh. The offset stays until the next step.
- generic receivers (ground stations): the estimator's frame as it is, ``MAV_FRAME_LOCAL_NED``.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from vtolpose.drivers.links.mavlink_wire import mavutil
from vtolpose.estimator import OutputPose, quat_mul, quat_to_rot, yaw_of

__all__ = ["PublishedFrame", "turned_about_down"]

mav = mavutil.mavlink


def turned_about_down(pose: OutputPose, angle_rad: float) -> OutputPose:
    """``pose`` in a frame turned by ``angle_rad`` about the down axis: position, velocity, attitude and
    the world-frame covariance blocks turned with it; body quantities unchanged."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    t9 = np.kron(np.eye(3), rz)
    half = 0.5 * angle_rad
    q = quat_mul(np.array([math.cos(half), 0.0, 0.0, math.sin(half)]), pose.q)
    cov9 = t9 @ pose.cov9 @ t9.T
    index = np.r_[0:3, 6:9]
    return replace(pose, p=rz @ pose.p, v=rz @ pose.v, q=q, cov9=cov9, pose_cov=cov9[np.ix_(index, index)])


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


class PublishedFrame:
    """One autopilot profile's view of the pose's frame. :meth:`follow` sees every pose (the steps are
    found between consecutive poses); :meth:`present` makes the pose and fields of one ODOMETRY."""

    def __init__(self, profile_name: str) -> None:
        self.profile_name = profile_name
        self.frame_changes = 0  # steps added to the estimator's reset_counter
        self.yaw_offset = 0.0  # ArduPilot: the published frame's turn from the estimator's [rad]
        self.yaw_steps_absorbed = 0
        self._last: OutputPose | None = None

    def follow(self, pose: OutputPose) -> None:
        last = self._last
        self._last = pose
        if last is None or self.profile_name == "generic":
            return
        aligned_changed = pose.heading_aligned != last.heading_aligned
        if self.profile_name == "px4":
            self.frame_changes += aligned_changed
        elif aligned_changed or pose.reset_counter != last.reset_counter:
            self._absorb_yaw_step(last, pose)
            self.frame_changes += aligned_changed

    def _absorb_yaw_step(self, last: OutputPose, pose: OutputPose) -> None:
        """The offset that continues the published yaw across the step (the last one carried on at its rate)."""
        yaw_rate = float((quat_to_rot(last.q) @ last.omega_b)[2])
        expected = float(yaw_of(last.q)) + self.yaw_offset + yaw_rate * (pose.t_ns - last.t_ns) * 1e-9
        before = self.yaw_offset
        self.yaw_offset = _wrap(expected - float(yaw_of(pose.q)))
        if abs(_wrap(self.yaw_offset - before)) > 1e-3:
            self.yaw_steps_absorbed += 1

    def present(self, pose: OutputPose) -> tuple[OutputPose, int, int]:
        """(pose as published, ``frame_id``, ``reset_counter`` before the modulo)."""
        counter = pose.reset_counter + self.frame_changes
        if self.profile_name == "px4":
            return pose, mav.MAV_FRAME_LOCAL_NED if pose.heading_aligned else mav.MAV_FRAME_LOCAL_FRD, counter
        if self.profile_name == "ardupilot":
            shown = turned_about_down(pose, self.yaw_offset) if self.yaw_offset != 0.0 else pose
            return shown, mav.MAV_FRAME_LOCAL_FRD, counter
        return pose, mav.MAV_FRAME_LOCAL_NED, counter

    def report(self) -> dict[str, float | int]:
        doc: dict[str, float | int] = {"frame_changes": self.frame_changes}
        if self.profile_name == "ardupilot":
            doc.update(yaw_offset_deg=round(math.degrees(self.yaw_offset), 3), yaw_steps_absorbed=self.yaw_steps_absorbed)
        return doc
