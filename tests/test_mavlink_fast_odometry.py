"""ODOMETRY framed without pymavlink's message objects: the same bytes as pymavlink's, frame for frame.

pymavlink is the reference. Random poses (unusable ones and unknown covariances among them) for every
autopilot profile go out both ways, signed and unsigned, over several sequence-number wrap-arounds,
with HEARTBEATs and STATUSTEXTs through pymavlink in between; a pymavlink receiver then parses what
the fast path wrote, checking the signatures when signed.
"""

import dataclasses
import math
import socket
import time

import numpy as np
import pytest

from vtolpose.config.mavlink_settings import EndpointSpec
from vtolpose.drivers.links.mavlink_outbound import frame_v2, send_v2
from vtolpose.estimator.core.rotation import quat_from_euler, quat_to_rot, skew
from vtolpose.estimator.fusion import OutputPose
from vtolpose.service.outputs import mavlink_output as mavlink_output
from vtolpose.service.outputs.mavlink_output import (
    COMPONENT_ID, Endpoint, MavlinkOutput, euler_jacobian, mavutil, odometry_covariances, odometry_fields,
)
from vtolpose.service.outputs.mavlink_frame import PublishedFrame
from vtolpose.service.outputs.mavlink_odometry import ODOMETRY_CRC_EXTRA, ODOMETRY_ID, PROFILES, odometry_payload

mav = mavutil.mavlink
POSE = [0, 1, 2, 6, 7, 8]  # position and attitude rows of the 9 × 9 [δp, δv, δθ] covariance
KEY = bytes(range(3, 35))
# An all-NaN covariance is among the random poses; numpy says so while the ODOMETRY covariance is mapped.
pytestmark = pytest.mark.filterwarnings("ignore:invalid value encountered in matmul:RuntimeWarning")
START_TIMESTAMP = 370_000_000_000_000  # a signing clock in 2026 (10 µs units since 2015)


class Frames:
    """A pymavlink link's ``file``: keeps what is written."""

    def __init__(self) -> None:
        self.written: list[bytes] = []

    def write(self, buf: bytes) -> None:
        self.written.append(bytes(buf))


def random_pose(rng: np.random.Generator) -> OutputPose:
    """A pose with anything the estimator may publish: usable or not, covariance known or not."""
    a = rng.normal(size=(9, 9)) * 10.0 ** rng.uniform(-4, 0)
    cov9 = a @ a.T + np.diag(10.0 ** rng.uniform(-6, 2, 9))
    kind = rng.integers(10)
    if kind == 0:  # unknown somewhere off the position and attitude diagonals: usable, covariance all NaN
        cov9[3, 4] = cov9[4, 3] = math.nan
    elif kind == 1:  # not finite on the position diagonal: an unusable pose
        cov9[1, 1] = math.inf
    elif kind == 2:
        cov9[:] = math.nan
    q = quat_from_euler(*rng.uniform(-math.pi, math.pi, 3) * (0.45, 0.45, 1.0))
    t_ns = int(rng.integers(0, 2**52))
    flags = rng.random(4) < (0.9, 0.9, 0.1, 0.1)  # positioned, aligned, local position, health 0
    return OutputPose(t_ns, rng.normal(size=3) * 10.0 ** rng.uniform(-2, 4), rng.normal(size=3) * 20.0, q,
                      rng.normal(size=3), cov9, cov9[np.ix_(POSE, POSE)], 10.0 ** rng.uniform(-8, -2, 3),
                      bool(flags[1]), bool(flags[0]), int(rng.integers(0, 1000)), t_ns - int(rng.integers(0, 10**8)),
                      0 if flags[3] else int(rng.integers(1, 101)), bool(flags[2]))


def zero_tail_fields(rng: np.random.Generator) -> dict:
    """Fields whose payload ends in zero bytes (MAVLink 2 cuts them), down to an all-zero payload."""
    zeros = int(rng.integers(0, 56))
    values = list(rng.normal(size=55))
    values[55 - zeros:] = [0.0] * zeros
    return dict(time_usec=0 if zeros == 55 else int(rng.integers(0, 2**63)), x=values[0], y=values[1], z=values[2],
                q=values[3:7], vx=values[7], vy=values[8], vz=values[9], rollspeed=values[10], pitchspeed=values[11],
                yawspeed=values[12], pose_covariance=values[13:34], velocity_covariance=values[34:55],
                frame_id=0, child_frame_id=0, reset_counter=0, estimator_type=0, quality=0)


def twin_links(signed: bool, system_id: int, link_id: int) -> tuple:
    """Two pymavlink links in the same state: one sends through pymavlink, the other through the fast path."""
    links = []
    for _ in range(2):
        tx = mav.MAVLink(Frames(), srcSystem=system_id, srcComponent=COMPONENT_ID)
        if signed:
            tx.signing.secret_key, tx.signing.sign_outgoing = KEY, True
            tx.signing.link_id, tx.signing.timestamp = link_id, START_TIMESTAMP
        links.append(tx)
    return tuple(links)


def receiver(signed: bool):
    rx = mav.MAVLink(None)
    rx.robust_parsing = True
    if signed:
        rx.signing.secret_key = KEY
        rx.signing.allow_unsigned_callback = lambda _mav, _msg_id: False
    return rx


def assert_same_frames(signed: bool, seed: int, count: int = 700, crc_extra: int = ODOMETRY_CRC_EXTRA) -> None:
    """``count`` ODOMETRY both ways (HEARTBEAT and STATUSTEXT through pymavlink between them), then parsed."""
    rng = np.random.default_rng(seed)
    ref, fast = twin_links(signed, int(rng.integers(1, 256)), int(rng.integers(0, 256)))
    profiles = list(PROFILES.values())
    sent_fields = []
    for i in range(count):
        f = odometry_fields(random_pose(rng), profiles[i % 3]) if i % 10 else zero_tail_fields(rng)
        sent_fields.append(f)
        ref.send(mav.MAVLink_odometry_message(**f))
        send_v2(fast, ODOMETRY_ID, crc_extra, odometry_payload(f))
        assert fast.file.written[-1] == ref.file.written[-1], f"frame {len(ref.file.written) - 1} (seed {seed})"
        if i % 7 == 0:
            beat = mav.MAVLink_heartbeat_message(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0, 4, 3)
            ref.send(beat)
            fast.send(beat)
        if i % 50 == 0:
            text = mav.MAVLink_statustext_message(mav.MAV_SEVERITY_INFO, b"heading aligned", 0, 0)
            ref.send(text)
            fast.send(text)
        if signed and i % 40 == 0:  # the endpoint moves the timestamp up to its clock now and then
            ref.signing.timestamp = fast.signing.timestamp = ref.signing.timestamp + int(rng.integers(1, 10**6))
    assert fast.file.written == ref.file.written
    state = ("seq", "total_packets_sent", "total_bytes_sent")
    assert [getattr(fast, s) for s in state] == [getattr(ref, s) for s in state]
    assert fast.signing.timestamp == ref.signing.timestamp

    rx = receiver(signed)
    frames = fast.file.written
    got = rx.parse_buffer(b"".join(frames))
    assert [m.get_type() for m in got if m.get_type() == "BAD_DATA"] == []
    assert len(got) == len(frames)
    assert [m.get_seq() for m in got] == [(ref.seq - len(frames) + k) % 256 for k in range(len(frames))]
    if signed:
        assert (rx.signing.goodsig_count, rx.signing.badsig_count) == (len(frames), 0)
    odometry = [m for m in got if m.get_type() == "ODOMETRY"]
    assert len(odometry) == count
    for msg, f in zip(odometry, sent_fields):
        assert (msg.time_usec, msg.frame_id, msg.reset_counter, msg.quality) == (f["time_usec"], f["frame_id"],
                                                                                  f["reset_counter"], f["quality"])
        np.testing.assert_array_equal(msg.pose_covariance, np.float32(f["pose_covariance"]))
        np.testing.assert_array_equal(msg.q, np.float32(f["q"]))


def test_the_fields_are_the_plain_products_of_the_estimators_covariance():
    """The per-pose fast arithmetic against the definitions written out with whole matrices."""
    rng = np.random.default_rng(21)
    triu = np.triu_indices(6)
    checked = 0
    while checked < 200:
        pose = random_pose(rng)
        f = odometry_fields(pose, PROFILES["generic"])
        if f["quality"] < 0 or math.isnan(f["pose_covariance"][0]) or math.isnan(f["velocity_covariance"][0]):
            continue
        r = quat_to_rot(pose.q)
        to_euler = np.eye(6)
        to_euler[3:, 3:] = euler_jacobian(pose.q)
        pose_cov = to_euler @ pose.cov9[np.ix_(POSE, POSE)] @ to_euler.T
        jv = np.hstack([r.T, r.T @ skew(pose.v)])
        vel_cov = np.zeros((6, 6))
        vel_cov[:3, :3] = jv @ pose.cov9[3:9, 3:9] @ jv.T
        vel_cov[3:, 3:] = np.diag(pose.omega_var)
        np.testing.assert_allclose(f["pose_covariance"], pose_cov[triu], rtol=1e-9, atol=1e-15 * np.abs(pose_cov).max())
        np.testing.assert_allclose(f["velocity_covariance"], vel_cov[triu], rtol=1e-9, atol=1e-15 * np.abs(vel_cov).max())
        np.testing.assert_allclose([f["vx"], f["vy"], f["vz"]], r.T @ pose.v, rtol=1e-12, atol=1e-12)
        for got, want in zip(odometry_covariances(pose), (pose_cov, vel_cov)):
            np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-15 * np.abs(want).max())
        checked += 1


@pytest.mark.parametrize("signed", [False, True], ids=["unsigned", "signed"])
def test_fast_odometry_frames_are_pymavlinks_byte_for_byte(signed):
    assert_same_frames(signed, seed=11 + signed)


def test_a_wrong_crc_extra_is_caught_by_the_comparison_and_refused_by_pymavlink():
    with pytest.raises(AssertionError, match="frame 0"):
        assert_same_frames(False, seed=5, count=3, crc_extra=ODOMETRY_CRC_EXTRA ^ 0x10)
    tx = mav.MAVLink(Frames(), srcSystem=1, srcComponent=COMPONENT_ID)
    wrong = frame_v2(tx, ODOMETRY_ID, ODOMETRY_CRC_EXTRA ^ 0x10, odometry_payload(zero_tail_fields(np.random.default_rng(1))))
    assert [m.get_type() for m in receiver(False).parse_buffer(wrong)] == ["BAD_DATA"]


def test_a_frame_signed_with_another_key_is_refused():
    tx = mav.MAVLink(Frames(), srcSystem=1, srcComponent=COMPONENT_ID)
    tx.signing.secret_key, tx.signing.sign_outgoing, tx.signing.timestamp = bytes(32), True, START_TIMESTAMP
    frame = frame_v2(tx, ODOMETRY_ID, ODOMETRY_CRC_EXTRA, odometry_payload(zero_tail_fields(np.random.default_rng(2))))
    rx = receiver(True)
    assert [m.get_type() for m in rx.parse_buffer(frame)] == ["BAD_DATA"] and rx.signing.badsig_count == 1


def drain(sock: socket.socket, into: list[bytes], want: int, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while len(into) < want and time.monotonic() < deadline:
        try:
            into.append(sock.recv(4096))
        except BlockingIOError:
            time.sleep(0.001)
    assert len(into) == want, f"{len(into)} of {want} datagrams arrived"


def test_the_output_sends_pymavlinks_bytes_and_keeps_the_links_sequence_and_signing():
    """Through :class:`MavlinkOutput` over loopback: every ODOMETRY is what pymavlink would have framed in
    the link's state at that moment, and the link's sequence and signing timestamps run on unbroken
    through the HEARTBEATs and STATUSTEXTs pymavlink sends between them."""
    sinks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
    for s in sinks:
        s.bind(("127.0.0.1", 0))
        s.setblocking(False)
    specs = [EndpointSpec("fc", f"udpout:127.0.0.1:{sinks[0].getsockname()[1]}", "autopilot", 40.0, None, False, "fc"),
             EndpointSpec("gcs", f"udpout:127.0.0.1:{sinks[1].getsockname()[1]}", "ground_station", 40.0, None, False, "gcs")]
    out = MavlinkOutput([Endpoint(specs[0], KEY, PROFILES["ardupilot"], 42, COMPONENT_ID),
                         Endpoint(specs[1], None, PROFILES["ardupilot"], 42, COMPONENT_ID)], "ardupilot")
    rng = np.random.default_rng(3)
    poses, received = [], [[], []]
    out.open()
    try:
        t_ns = 10**12
        for i in range(600):
            t_ns += 25_000_000
            pose = dataclasses.replace(random_pose(rng), t_ns=t_ns, fused_t_ns=t_ns)
            assert out.publish(pose)
            poses.append(pose)
            extra = 0
            if i % 9 == 0:
                out.heartbeat()
                extra += 1
            if i % 97 == 0:
                out.statustext(mav.MAV_SEVERITY_INFO, f"note {i}")
                extra += 1
            for sink, got in zip(sinks, received):
                drain(sink, got, len(got) + 1 + extra)
    finally:
        out.close()
        for s in sinks:
            s.close()
    for signed, frames in zip((True, False), received):
        seqs = [f[4] for f in frames]
        assert all(b == (a + 1) % 256 for a, b in zip(seqs, seqs[1:])) and len(frames) > 2 * 256
        if signed:
            stamps = [int.from_bytes(f[-12:-6], "little") for f in frames]
            assert all(b > a for a, b in zip(stamps, stamps[1:]))
        rx = receiver(signed)
        msgs = rx.parse_buffer(b"".join(frames))
        assert len(msgs) == len(frames) and not [m for m in msgs if m.get_type() == "BAD_DATA"]
        if signed:
            assert rx.signing.goodsig_count == len(frames)
        odometry = [f for f, m in zip(frames, msgs) if m.get_type() == "ODOMETRY"]
        assert len(odometry) == len(poses)
        profile = PROFILES["ardupilot"] if signed else PROFILES["generic"]  # a ground station gets the generic fields
        published = PublishedFrame(profile.name)  # the frame the profile is told (ArduPilot's yaw held across steps)
        for frame, pose in zip(odometry, poses):
            published.follow(pose)
            ref = mav.MAVLink(Frames(), srcSystem=42, srcComponent=COMPONENT_ID)
            ref.seq = frame[4]
            if signed:
                ref.signing.secret_key, ref.signing.sign_outgoing = KEY, True
                ref.signing.link_id, ref.signing.timestamp = frame[-13], int.from_bytes(frame[-12:-6], "little")
            shown, frame_id, resets = published.present(pose)
            ref.send(mav.MAVLink_odometry_message(**odometry_fields(shown, profile, frame_id, resets)))
            assert frame == ref.file.written[0]


def test_publish_uses_the_odometry_crc_extra_it_was_given(monkeypatch):
    """The output test above compares against pymavlink: it fails when the output's framing diverges."""
    monkeypatch.setattr(mavlink_output, "ODOMETRY_CRC_EXTRA", ODOMETRY_CRC_EXTRA + 1)
    with pytest.raises(AssertionError):
        test_the_output_sends_pymavlinks_bytes_and_keeps_the_links_sequence_and_signing()
