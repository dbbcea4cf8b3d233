"""The frame each autopilot is told, as a pymavlink peer on loopback receives it: PX4 gets LOCAL_FRD while the
heading is not north-referenced and a reset_counter step when that changes; ArduPilot never sees the yaw
step (the published frame absorbs it), and the reset_counter steps when the frame changes."""

from __future__ import annotations

import dataclasses
import math
import socket

import numpy as np
import pytest

from vtolpose.estimator.core.rotation import quat_from_euler
from vtolpose.service.outputs.mavlink_output import MavlinkOutput, mavutil
from vtolpose.service.outputs.mavlink_frame import PublishedFrame, turned_about_down

from test_mavlink_out import endpoint, make_pose

mav = mavutil.mavlink
PERIOD_NS = 20_000_000  # 50 Hz: every pose below is sent


def camera_only(pose, **kw):
    """The pose of a camera-only filter that never heard a GPS: its own frame, heading not placed."""
    return dataclasses.replace(pose, heading_aligned=False, local_position=True, **kw)


def send_all(autopilot: str, poses: list) -> tuple[list, MavlinkOutput]:
    """Every pose through a MavlinkOutput to a UDP peer; the ODOMETRY the peer decoded, in order."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(1.0)
    rate = 30.0 if autopilot == "ardupilot" else 50.0
    out = MavlinkOutput([endpoint(f"udpout:127.0.0.1:{sock.getsockname()[1]}", autopilot=autopilot, rate_hz=rate)],
                        autopilot)
    out.open()
    decoder, received = mav.MAVLink(None), []
    try:
        for pose in poses:
            out.publish(pose)
            while True:
                try:
                    data = sock.recv(65535)
                except socket.timeout:
                    raise AssertionError("an ODOMETRY did not arrive") from None
                msgs = [m for m in decoder.parse_buffer(data) or [] if m.get_type() == "ODOMETRY"]
                if msgs:
                    received += msgs
                    break
    finally:
        out.close()
        sock.close()
    return received, out


def poses_at(n: int, t0: int = 10**12, period_ns: int = 40_000_000, **kw) -> list:
    return [make_pose(t_ns=t0 + k * period_ns, **kw) for k in range(n)]


def test_px4_a_camera_only_pose_goes_out_as_local_frd_and_usable():
    msgs, _ = send_all("px4", [camera_only(p) for p in poses_at(5)])
    assert {m.frame_id for m in msgs} == {mav.MAV_FRAME_LOCAL_FRD}
    assert all(m.quality >= 1 and math.isfinite(m.x) for m in msgs)  # usable, in a frame of its own
    assert {m.reset_counter for m in msgs} == {3}


def test_px4_a_north_referenced_pose_goes_out_as_local_ned():
    msgs, _ = send_all("px4", poses_at(5))
    assert {m.frame_id for m in msgs} == {mav.MAV_FRAME_LOCAL_NED} and {m.reset_counter for m in msgs} == {3}


def test_px4_the_frame_switches_with_a_reset_counter_step_when_the_heading_is_placed():
    poses = poses_at(8)
    poses = [camera_only(p) for p in poses[:4]] + poses[4:]  # a GPS places the heading: the estimator's counter stays 3
    msgs, out = send_all("px4", poses)
    assert [m.frame_id for m in msgs] == [mav.MAV_FRAME_LOCAL_FRD] * 4 + [mav.MAV_FRAME_LOCAL_NED] * 4
    assert [m.reset_counter for m in msgs] == [3] * 4 + [4] * 4
    assert out.link_stats()["frames"]["px4"]["frame_changes"] == 1


def yaw_deg(m) -> float:
    w, x, y, z = m.q
    return math.degrees(math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


def turning(n: int, yaw0_deg: float, rate_deg_s: float, t0: int, period_ns: int = 40_000_000, **kw) -> list:
    """Poses of a vehicle turning at a steady rate about the vertical (level, rates in the body frame)."""
    out = []
    for k in range(n):
        yaw = math.radians(yaw0_deg + rate_deg_s * k * period_ns * 1e-9)
        pose = make_pose(t_ns=t0 + k * period_ns, **kw)
        out.append(dataclasses.replace(pose, q=quat_from_euler(0.0, 0.0, yaw),
                                       omega_b=np.array([0.0, 0.0, math.radians(rate_deg_s)])))
    return out


@pytest.mark.parametrize("step", ["reset", "gps joins a camera-only frame"])
def test_ardupilot_never_sees_a_yaw_step(step):
    before = turning(10, 20.0, 5.0, 10**12)
    after = turning(10, 20.0 + 5.0 * 0.4 + 95.0, 5.0, 10**12 + 400_000_000)  # the heading jumps 95° at the step
    if step == "reset":
        after = [dataclasses.replace(p, reset_counter=4) for p in after]
    else:
        before = [camera_only(p) for p in before]
    msgs, out = send_all("ardupilot", before + after)
    assert {m.frame_id for m in msgs} == {mav.MAV_FRAME_LOCAL_FRD}
    yaws = np.array([yaw_deg(m) for m in msgs])
    steps = np.diff(yaws)
    assert np.allclose(steps, 5.0 * 0.04, atol=0.01), steps  # 0.2° a message: the turn, and nothing else
    assert [m.reset_counter for m in msgs] == [3] * 10 + [4] * 10  # the position is taken afresh
    frames = out.link_stats()["frames"]["ardupilot"]
    assert frames["yaw_steps_absorbed"] == 1 and frames["yaw_offset_deg"] == pytest.approx(-95.0, abs=0.01)
    # the published frame is the estimator's turned by the offset: position and velocity turn with it
    last, msg = after[-1], msgs[-1]
    c, s = math.cos(math.radians(-95.0)), math.sin(math.radians(-95.0))
    assert [msg.x, msg.y, msg.z] == pytest.approx([c * last.p[0] - s * last.p[1], s * last.p[0] + c * last.p[1], last.p[2]],
                                                  abs=1e-3)


def test_turning_a_pose_turns_its_world_covariance_and_keeps_its_body_quantities():
    pose = make_pose()
    turned = turned_about_down(pose, math.radians(30.0))
    c, s = math.cos(math.radians(30.0)), math.sin(math.radians(30.0))
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    assert np.allclose(turned.p, rz @ pose.p) and np.allclose(turned.v, rz @ pose.v)
    assert np.allclose(turned.cov9[0:3, 0:3], rz @ pose.cov9[0:3, 0:3] @ rz.T)
    assert np.allclose(turned.cov9[6:9, 0:3], rz @ pose.cov9[6:9, 0:3] @ rz.T)
    assert np.array_equal(turned.omega_b, pose.omega_b) and np.array_equal(turned.omega_var, pose.omega_var)
    frame = PublishedFrame("generic")
    for p in poses_at(3):
        frame.follow(p)
    assert frame.present(p)[1:] == (mav.MAV_FRAME_LOCAL_NED, p.reset_counter)  # ground stations: as it is
