"""MAVLink output: ODOMETRY fields as INTERFACES.md says, and real pymavlink peers over UDP loopback
(HEARTBEAT, ODOMETRY, signing in both directions)."""

import math
import socket
import time

import numpy as np
import pytest

from vtolpose.estimator.fusion import OutputPose
from vtolpose.estimator.core.rotation import euler_from_quat, quat_exp, quat_from_euler, quat_mul, quat_to_rot
from vtolpose.service.outputs.mavlink import (
    COMPONENT_ID, MavlinkOutput, SigningKeyError, euler_jacobian, mavutil, odometry_covariances, odometry_fields,
    read_signing_key,
)
from vtolpose.service.runtime.status import pose_quality

mav = mavutil.mavlink
TRIU_DIAG = [0, 6, 11, 15, 18, 20]  # where the diagonal sits in the 21-value upper triangle
POSE = [0, 1, 2, 6, 7, 8]  # position and attitude rows of the 9 × 9 [δp, δv, δθ] covariance


def make_pose(t_ns=5_000_000_000, sigma_p=0.05, sigma_a_deg=0.3, aligned=True, cov9=None) -> OutputPose:
    rng = np.random.default_rng(1)
    if cov9 is None:
        a = rng.normal(size=(9, 9)) * 0.1
        cov9 = a @ a.T * 1e-6
        cov9[0:3, 0:3] += np.eye(3) * sigma_p**2
        cov9[6:9, 6:9] += np.eye(3) * math.radians(sigma_a_deg) ** 2
    return OutputPose(t_ns, np.array([10.0, -4.0, -30.0]), np.array([6.0, 1.5, -0.4]), quat_from_euler(0.1, -0.2, 2.5),
                      np.array([0.01, -0.02, 0.3]), cov9, cov9[np.ix_(POSE, POSE)], np.array([1e-4, 2e-4, 3e-4]), aligned, True,
                      3, t_ns - 150_000_000)


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def receive(conn, kind: str, timeout_s: float = 5.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        msg = conn.recv_match(type=kind, blocking=True, timeout=0.1)
        if msg is not None:
            return msg
    return None


def test_odometry_fields_follow_the_interface():
    pose = make_pose()
    f = odometry_fields(pose)
    assert (f["frame_id"], f["child_frame_id"]) == (mav.MAV_FRAME_LOCAL_NED, mav.MAV_FRAME_BODY_FRD)
    assert f["estimator_type"] == mav.MAV_ESTIMATOR_TYPE_VIO and f["reset_counter"] == 3
    assert f["time_usec"] == 5_000_000
    assert [f["x"], f["y"], f["z"]] == pose.p.tolist() and f["q"] == pose.q.tolist()
    assert np.allclose([f["vx"], f["vy"], f["vz"]], quat_to_rot(pose.q).T @ pose.v)
    assert [f["rollspeed"], f["pitchspeed"], f["yawspeed"]] == pose.omega_b.tolist()
    assert len(f["pose_covariance"]) == 21 and len(f["velocity_covariance"]) == 21
    pose_cov, vel_cov = odometry_covariances(pose)
    assert np.allclose(np.array(f["pose_covariance"])[TRIU_DIAG], np.diag(pose_cov))
    assert np.allclose(np.array(f["pose_covariance"])[:3], pose.cov9[0, 0:3])  # row-major, first row
    assert np.allclose(np.array(f["velocity_covariance"])[TRIU_DIAG[3:]], pose.omega_var)
    assert 0 < f["quality"] <= 100


def test_attitude_block_is_mapped_to_roll_pitch_yaw():
    """Finite differences of the Euler angles under a world-frame rotation give the mapping used."""
    q = quat_from_euler(0.3, -0.4, 2.0)
    h = 1e-7
    numeric = np.column_stack([
        (euler_from_quat(quat_mul(quat_exp(h * e), q)) - euler_from_quat(quat_mul(quat_exp(-h * e), q))) / (2 * h)
        for e in np.eye(3)
    ])
    assert np.allclose(euler_jacobian(q), numeric, atol=1e-6)
    assert np.allclose(euler_jacobian(np.array([1.0, 0, 0, 0])), np.eye(3))


def test_body_velocity_covariance_includes_the_attitude_error():
    cov9 = np.zeros((9, 9))
    cov9[3:9, 3:9] = np.eye(6)  # unit velocity and attitude errors: vel_cov = J Jᵀ
    pose = make_pose(cov9=cov9)
    r = quat_to_rot(pose.q)
    h = 1e-6
    cols = []
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        plus = quat_to_rot(quat_mul(quat_exp(d[3:]), pose.q)).T @ (pose.v + d[:3])
        minus = quat_to_rot(quat_mul(quat_exp(-d[3:]), pose.q)).T @ (pose.v - d[:3])
        cols.append((plus - minus) / (2 * h))
    jac = np.column_stack(cols)
    _, vel_cov = odometry_covariances(pose)
    assert np.allclose(vel_cov[0:3, 0:3], jac @ jac.T, atol=1e-6)
    assert np.allclose(jac[:, :3], r.T)


def test_quality_is_zero_when_invalid_and_falls_with_uncertainty():
    assert pose_quality(make_pose(aligned=False)) == 0
    nan = make_pose()
    nan.cov9[0, 0] = np.nan
    assert pose_quality(nan) == 0
    good, fair, poor = (pose_quality(make_pose(sigma_p=s)) for s in (0.01, 1.0, 50.0))
    assert good == 100 and 1 <= poor < fair < good
    assert pose_quality(make_pose(sigma_a_deg=10.0)) < good


def test_a_udp_peer_receives_heartbeat_and_odometry():
    port = free_udp_port()
    peer = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=1)
    out = MavlinkOutput(f"udpout:127.0.0.1:{port}", system_id=7, rate_hz=50.0)
    out.open()
    try:
        out.heartbeat()
        beat = receive(peer, "HEARTBEAT")
        assert beat is not None
        assert (beat.type, beat.autopilot) == (mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID)
        assert (beat.get_srcSystem(), beat.get_srcComponent()) == (7, COMPONENT_ID)
        pose = make_pose()
        sent = [out.publish(make_pose(t_ns=pose.t_ns + dt)) for dt in (0, 5_000_000, 20_000_000)]
        assert sent == [True, False, True]  # 50 Hz: the sample 5 ms later is not sent
        msg = receive(peer, "ODOMETRY")
        expected = odometry_fields(pose)
        assert msg.time_usec == expected["time_usec"] and msg.reset_counter == 3 and msg.quality == expected["quality"]
        assert (msg.frame_id, msg.child_frame_id, msg.estimator_type) == (mav.MAV_FRAME_LOCAL_NED, mav.MAV_FRAME_BODY_FRD,
                                                                       mav.MAV_ESTIMATOR_TYPE_VIO)
        for key in ("x", "y", "z", "vx", "vy", "vz", "rollspeed", "pitchspeed", "yawspeed"):
            assert getattr(msg, key) == pytest.approx(expected[key], rel=1e-6, abs=1e-6), key
        assert np.allclose(msg.q, expected["q"], atol=1e-7)
        assert np.allclose(msg.pose_covariance, expected["pose_covariance"], rtol=1e-6, atol=1e-12)
        assert np.allclose(msg.velocity_covariance, expected["velocity_covariance"], rtol=1e-6, atol=1e-12)
        assert msg.get_header().srcComponent == COMPONENT_ID and msg.get_msgbuf()[0] == 0xFD  # MAVLink 2
    finally:
        out.close()
        peer.close()


@pytest.fixture
def key_files(tmp_path):
    good, wrong = tmp_path / "good.key", tmp_path / "wrong.key"
    good.write_bytes(bytes(range(32)))
    wrong.write_text(bytes(range(1, 33)).hex() + "\n")
    return good, wrong


def test_signing_keys_are_read_and_checked(key_files, tmp_path):
    good, wrong = key_files
    assert read_signing_key(good) == bytes(range(32))
    assert read_signing_key(wrong) == bytes(range(1, 33))
    (tmp_path / "short.key").write_bytes(b"x" * 31)
    with pytest.raises(SigningKeyError, match="short.key.*32 raw bytes"):
        read_signing_key(tmp_path / "short.key")
    with pytest.raises(SigningKeyError, match="missing.key"):
        read_signing_key(tmp_path / "missing.key")
    (tmp_path / "nothex.key").write_text("z" * 64)
    with pytest.raises(SigningKeyError, match="nothex.key: 64 characters, but not hexadecimal"):
        read_signing_key(tmp_path / "nothex.key")


def test_signed_output_is_accepted_with_the_key_and_refused_without(key_files):
    key, wrong = (read_signing_key(p) for p in key_files)
    ports = free_udp_port(), free_udp_port()
    peers = [mavutil.mavlink_connection(f"udpin:127.0.0.1:{p}", source_system=1, source_component=1) for p in ports]
    for peer, peer_key in zip(peers, (key, wrong)):
        peer.setup_signing(peer_key, sign_outgoing=True, allow_unsigned_callback=lambda _m, _id: False)
    outs = [MavlinkOutput(f"udpout:127.0.0.1:{p}", system_id=7, signing_key=key) for p in ports]
    try:
        for out in outs:
            out.open()
            out.heartbeat()
        assert receive(peers[0], "HEARTBEAT") is not None
        assert peers[0].mav.signing.goodsig_count >= 1
        assert receive(peers[1], "HEARTBEAT", timeout_s=1.0) is None
        assert peers[1].mav.signing.badsig_count >= 1
    finally:
        for c in outs + peers:
            c.close()


def test_required_signing_refuses_unsigned_and_wrongly_signed_messages(key_files):
    key, wrong = (read_signing_key(p) for p in key_files)
    port = free_udp_port()
    out = MavlinkOutput(f"udpout:127.0.0.1:{port}", system_id=7, signing_key=key, require_signing=True)
    seen = []
    out.handlers["GPS_RAW_INT"] = seen.append
    peer = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=1)
    out.open()
    try:
        out.heartbeat()  # the peer learns where we are (it has no key yet, so it takes the signed message)
        assert receive(peer, "HEARTBEAT") is not None

        def send(signing_key, sats):
            if signing_key is None:
                peer.disable_signing()
            else:
                peer.setup_signing(signing_key, sign_outgoing=True)
            peer.mav.gps_raw_int_send(1, 3, 584300000, 156800000, 60000, 100, 150, 0, 0, sats)

        def settle(n_expected: int, timeout_s: float = 5.0) -> None:
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                out.poll()
                stats = out.link_stats()
                if stats["received"] + stats["refused"] + stats["bad_data"] >= n_expected:
                    return
                time.sleep(0.01)

        send(None, 5)
        send(wrong, 6)
        send(key, 7)
        settle(3)
        stats = out.link_stats()
        assert [m.satellites_visible for m in seen] == [7]
        assert stats["received"] == 1 and stats["refused"] == 2 and stats["bad_signatures"] == 1
    finally:
        out.close()
        peer.close()
