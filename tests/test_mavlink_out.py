"""MAVLink output: ODOMETRY fields per autopilot, the send schedule, and real pymavlink peers over
loopback (HEARTBEAT, ODOMETRY, STATUSTEXT, signing both ways, several endpoints, serial and TCP)."""

import math
import os
import pty
import socket
import time

import numpy as np
import pytest

from vtolpose.config import ConfigError, load_config
from vtolpose.config.sections import build_sections
from vtolpose.config.mavlink_settings import EndpointSpec
from vtolpose.drivers.links.mavlink_signing import SignatureCheck
from vtolpose.estimator.core.rotation import euler_from_quat, quat_exp, quat_from_euler, quat_mul, quat_to_rot
from vtolpose.estimator.fusion import OutputPose
from vtolpose.service.outputs.mavlink_output import (
    COMPONENT_ID, Endpoint, MavlinkOutput, OdometrySchedule, SigningKeyError, euler_jacobian, mavutil,
    odometry_covariances, odometry_fields, read_signing_key,
)
from vtolpose.service.outputs.mavlink_odometry import PROFILES, odometry_quality
from vtolpose.service.runtime.status import pose_problem, pose_quality

from autopilot_rules import ardupilot_errors_known, ardupilot_fuses, px4_fused_parts, px4_variances_consistent

mav = mavutil.mavlink
TRIU_DIAG = [0, 6, 11, 15, 18, 20]  # where the diagonal sits in the 21-value upper triangle
POSE = [0, 1, 2, 6, 7, 8]  # position and attitude rows of the 9 × 9 [δp, δv, δθ] covariance


def make_pose(t_ns=5_000_000_000, sigma_p=0.05, sigma_a_deg=0.3, aligned=True, cov9=None, positioned=True, cap=100,
              resets=3) -> OutputPose:
    rng = np.random.default_rng(1)
    if cov9 is None:
        a = rng.normal(size=(9, 9)) * 0.1
        cov9 = a @ a.T * 1e-6
        cov9[0:3, 0:3] += np.eye(3) * sigma_p**2
        cov9[6:9, 6:9] += np.eye(3) * math.radians(sigma_a_deg) ** 2
    return OutputPose(t_ns, np.array([10.0, -4.0, -30.0]), np.array([6.0, 1.5, -0.4]), quat_from_euler(0.1, -0.2, 2.5),
                      np.array([0.01, -0.02, 0.3]), cov9, cov9[np.ix_(POSE, POSE)], np.array([1e-4, 2e-4, 3e-4]), aligned,
                      positioned, resets, t_ns - 150_000_000, cap)


def endpoint(url, name="fc", role="autopilot", rate_hz=50.0, key=None, require=False, autopilot="generic",
             system_id=7, **kw) -> Endpoint:
    return Endpoint(EndpointSpec(name, url, role, rate_hz, None, require, f"test {name}"), key, PROFILES[autopilot],
                    system_id, COMPONENT_ID, **kw)


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


def settle(out: MavlinkOutput, done, timeout_s: float = 10.0) -> None:
    """Poll ``out`` until ``done()`` (messages cross loopback asynchronously); fail saying so if it never is."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not done():
        out.poll()
        time.sleep(0.005)
    assert done(), f"what the peer sent was not handled within {timeout_s:g} s; link counters: {out.link_stats()}"


# ------------------------------------------------------------------------------------- fields


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


def test_each_autopilot_gets_its_frame_and_fuses_a_good_pose():
    pose = make_pose()
    px4, ardupilot = (mav.MAVLink_odometry_message(**odometry_fields(pose, PROFILES[name])) for name in ("px4", "ardupilot"))
    assert px4.frame_id == mav.MAV_FRAME_LOCAL_NED and ardupilot.frame_id == mav.MAV_FRAME_LOCAL_FRD
    assert px4_fused_parts(px4) == {"position", "attitude", "velocity"} and px4_variances_consistent(px4)
    assert ardupilot_fuses(ardupilot) and ardupilot_errors_known(ardupilot)
    generic = mav.MAVLink_odometry_message(**odometry_fields(pose))
    assert not ardupilot_fuses(generic)  # LOCAL_NED: ArduPilot's handle_odometry drops it


@pytest.mark.parametrize("why, pose", [
    ("heading not aligned", make_pose(aligned=False)),
    ("no position", make_pose(positioned=False)),
    ("covariance not finite", make_pose(cov9=np.full((9, 9), np.nan))),
    ("health", make_pose(cap=0)),
])
def test_an_unusable_pose_is_sent_so_that_no_default_autopilot_fuses_it(why, pose):
    assert pose_problem(pose) == why and pose_quality(pose) == 0 and odometry_quality(pose) == -1
    px4 = mav.MAVLink_odometry_message(**odometry_fields(pose, PROFILES["px4"]))
    assert px4.quality == -1 and px4_fused_parts(px4, ev_qmin=0) == set()  # NaN values: EKF2 takes nothing
    assert all(math.isnan(v) for v in list(px4.pose_covariance) + list(px4.velocity_covariance))
    ardupilot = mav.MAVLink_odometry_message(**odometry_fields(pose, PROFILES["ardupilot"]))
    assert ardupilot.quality == -1 and not ardupilot_fuses(ardupilot, qual_min=0)
    assert ardupilot_fuses(ardupilot, qual_min=-1) == math.isfinite(ardupilot.x)  # VISO_QUAL_MIN -1: "send bad values too"


def test_unknown_covariance_is_nan_everywhere():
    cov9 = np.eye(9) * 0.01
    cov9[4, 4] = np.inf  # the velocity block unknown, the pose block known
    f = odometry_fields(make_pose(cov9=cov9))
    assert all(math.isnan(v) for v in f["velocity_covariance"]) and np.all(np.isfinite(f["pose_covariance"]))
    msg = mav.MAVLink_odometry_message(**f)
    assert px4_variances_consistent(msg) and ardupilot_errors_known(msg)


def test_quality_falls_with_uncertainty_and_stays_under_the_health_cap():
    good, fair, poor = (pose_quality(make_pose(sigma_p=s)) for s in (0.01, 1.0, 50.0))
    assert good == 100 and 1 <= poor < fair < good
    assert pose_quality(make_pose(sigma_a_deg=10.0)) < good
    assert odometry_quality(make_pose(cap=20)) == 20


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


# ------------------------------------------------------------------------------------ schedule


def sends(schedule: OdometrySchedule, times) -> np.ndarray:
    return np.array([t for t in times if schedule.due(int(t))])


def test_the_schedule_keeps_the_configured_rate_on_imu_samples():
    imu = np.arange(0, 60_000_000_000, 8_000_000)  # 60 s at 125 Hz
    for rate in (50.0, 30.0, 40.0):
        sent = sends(OdometrySchedule(int(1e9 / rate)), imu)
        achieved = (len(sent) - 1) / ((sent[-1] - sent[0]) * 1e-9)
        assert achieved == pytest.approx(rate, rel=0.02), rate  # pose.t + period gave 41.7 Hz for 50
    ardupilot = sends(OdometrySchedule(int(1e9 / 40.0), PROFILES["ardupilot"].min_spacing_ns), imu)
    assert np.diff(ardupilot).min() >= 21_000_000  # EKF3 drops anything closer than 20 ms
    assert (len(ardupilot) - 1) / ((ardupilot[-1] - ardupilot[0]) * 1e-9) == pytest.approx(40.0, rel=0.02)


def test_the_schedule_restarts_after_a_hole_or_a_step_back():
    schedule = OdometrySchedule(20_000_000)
    assert schedule.due(0) and not schedule.due(10_000_000) and schedule.due(20_000_000)
    assert schedule.due(5_000_000_000) and not schedule.due(5_008_000_000)  # after a hole: no burst
    assert schedule.due(4_000_000_000)  # time went back (a clock step): send, and go on from there
    assert not schedule.due(4_010_000_000) and schedule.due(4_020_000_000)


# -------------------------------------------------------------------------- peers on loopback


def test_a_udp_peer_receives_heartbeat_and_odometry():
    port = free_udp_port()
    peer = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=1)
    out = MavlinkOutput([endpoint(f"udpout:127.0.0.1:{port}")])
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


def test_flight_controller_and_ground_station_each_get_their_stream_and_fail_alone():
    fc_port, gcs_port = free_udp_port(), free_udp_port()
    fc = mavutil.mavlink_connection(f"udpin:127.0.0.1:{fc_port}", source_system=7, source_component=1)
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{gcs_port}", source_system=255, source_component=190)
    out = MavlinkOutput([endpoint(f"udpout:127.0.0.1:{fc_port}", autopilot="ardupilot", rate_hz=30.0),
                         endpoint(f"udpout:127.0.0.1:{gcs_port}", name="gcs", role="ground_station", rate_hz=5.0,
                                  autopilot="ardupilot")])
    seen = []
    out.handlers["GPS_RAW_INT"] = seen.append
    out.open()
    try:
        t0 = 10_000_000_000
        for k in range(125):  # one second of 125 Hz poses
            out.publish(make_pose(t_ns=t0 + k * 8_000_000))
        fc_odometry = [m for m in iter(lambda: fc.recv_match(type="ODOMETRY", blocking=True, timeout=0.3), None)]
        gcs_odometry = [m for m in iter(lambda: gcs.recv_match(type="ODOMETRY", blocking=True, timeout=0.3), None)]
        assert len(fc_odometry) == 30 and len(gcs_odometry) == 5
        assert {m.frame_id for m in fc_odometry} == {mav.MAV_FRAME_LOCAL_FRD}  # the autopilot's profile
        assert {m.frame_id for m in gcs_odometry} == {mav.MAV_FRAME_LOCAL_NED}  # a ground station: generic
        # Only the flight controller's link feeds the estimator: a GPS_RAW_INT from the ground station is ignored.
        for peer in (gcs, fc):
            peer.mav.gps_raw_int_send(1, 3, 584300000, 156800000, 60000, 100, 150, 0, 0, 9)
        settle(out, lambda: out.link_stats()["received"] >= 2)
        assert len(seen) == 1 and seen[0].get_srcSystem() == 7
        # A ground-station link that breaks is counted; the flight controller's stream goes on.
        out.endpoints[1].transport.send = None  # calling it raises TypeError
        assert out.publish(make_pose(t_ns=t0 + 2_000_000_000))
        assert receive(fc, "ODOMETRY") is not None
        assert "failures" in out.link_stats()["endpoints"]["gcs"]
        out.statustext(mav.MAV_SEVERITY_WARNING, "gps stale")
        text = receive(fc, "STATUSTEXT")
        assert text.text == "vtolpose: gps stale" and text.severity == mav.MAV_SEVERITY_WARNING
    finally:
        out.close()
        fc.close()
        gcs.close()


def test_long_statustext_is_chunked_and_the_rate_is_limited():
    port = free_udp_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190)
    out = MavlinkOutput([endpoint(f"udpout:127.0.0.1:{port}", role="ground_station")], statustext_per_minute=6)
    out.open()
    try:
        long = "filter reset (gps_rejected): every GPS fix rejected for 5.0 s; re-initialised from GPS"
        whole = "w" * 90  # with "vtolpose: ", exactly two chunks: an empty third one ends it
        for n, text in ((2, long), (3, whole)):
            out.statustext(mav.MAV_SEVERITY_WARNING, text)
            chunks = [receive(gcs, "STATUSTEXT") for _ in range(n)]
            assert len({c.id for c in chunks}) == 1 and chunks[0].id > 0 and [c.chunk_seq for c in chunks] == list(range(n))
            assert "".join(c.text for c in chunks) == "vtolpose: " + text
        assert chunks[-1].text == "" and len("vtolpose: " + whole) == 100
        doc = {"heading_aligned": False, "filter_resets": 0, "health": {"sensors": {}}}
        for k in range(20):  # a flapping GPS: stale, back, stale, ...
            doc["health"]["sensors"]["gps"] = {"stale": k % 2 == 0}
            out.publish_status(dict(doc))
        texts = [m.text for m in iter(lambda: gcs.recv_match(type="STATUSTEXT", blocking=True, timeout=0.3), None)]
        assert texts[:2] == ["vtolpose: gps stale", "vtolpose: gps back"] and len(texts) == 5  # the burst, no more
        assert out.link_stats()["statustext_held_back"] == 15
    finally:
        out.close()
        gcs.close()


def test_why_the_visual_inertial_start_waits_goes_out_once_per_check():
    """While the start waits the operator hears why, with what it measured; a new figure under the same
    check is not news (it changes every half second), a new check is, and nothing once it has started."""
    port = free_udp_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190)
    out = MavlinkOutput([endpoint(f"udpout:127.0.0.1:{port}", role="ground_station")], statustext_per_minute=60)
    out.open()
    try:
        doc = {"heading_aligned": False, "filter_resets": 0, "health": {"sensors": {}}}
        scale = "initialising: 0.14 m/s^2 RMS over 5.0 s, scale sigma 40 %, scale not yet known (sigma over 25 %)"
        for text, check in ((scale, "scale"), (scale.replace("40 %", "31 %"), "scale"),
                            ("initialising: 0.16 m/s^2 RMS over 5.0 s, the camera moves against ...", "motion")):
            out.publish_status({**doc, "visual_start": {"check": check, "text": text}})
        out.publish_status(dict(doc))  # started: the status document no longer carries it
        chunks = [m for m in iter(lambda: gcs.recv_match(type="STATUSTEXT", blocking=True, timeout=0.3), None)]
        texts = "".join(m.text for m in chunks).split("vtolpose: ")[1:]
        assert texts == [scale, "initialising: 0.16 m/s^2 RMS over 5.0 s, the camera moves against ..."]
        assert {m.severity for m in chunks} == {mav.MAV_SEVERITY_INFO}
    finally:
        out.close()
        gcs.close()


# ------------------------------------------------------------------------------------- signing


@pytest.fixture
def key_files(tmp_path):
    good, wrong = tmp_path / "good.key", tmp_path / "wrong.key"
    good.write_bytes(bytes(range(32)))
    wrong.write_text(bytes(range(1, 33)).hex() + "\n")
    for path in (good, wrong):
        path.chmod(0o600)
    return good, wrong


def test_signing_keys_are_read_and_checked(key_files, tmp_path):
    good, wrong = key_files
    assert read_signing_key(good) == bytes(range(32))
    assert read_signing_key(wrong) == bytes(range(1, 33))
    for name, content in (("short.key", b"x" * 31), ("nothex.key", b"z" * 64)):
        (tmp_path / name).write_bytes(content)
        (tmp_path / name).chmod(0o600)
    with pytest.raises(SigningKeyError, match="short.key.*32 raw bytes"):
        read_signing_key(tmp_path / "short.key")
    with pytest.raises(SigningKeyError, match="missing.key"):
        read_signing_key(tmp_path / "missing.key")
    with pytest.raises(SigningKeyError, match="nothex.key: 64 characters, but not hexadecimal"):
        read_signing_key(tmp_path / "nothex.key")
    good.chmod(0o644)
    with pytest.raises(SigningKeyError, match=r"readable or writable by every user \(mode 0644\).*chmod 600"):
        read_signing_key(good)


def test_signed_output_is_accepted_with_the_key_and_refused_without(key_files):
    key, wrong = (read_signing_key(p) for p in key_files)
    ports = free_udp_port(), free_udp_port()
    peers = [mavutil.mavlink_connection(f"udpin:127.0.0.1:{p}", source_system=1, source_component=1) for p in ports]
    for peer, peer_key in zip(peers, (key, wrong)):
        peer.setup_signing(peer_key, sign_outgoing=True, allow_unsigned_callback=lambda _m, _id: False)
    out = MavlinkOutput([endpoint(f"udpout:127.0.0.1:{p}", name=f"fc{i}", key=key) for i, p in enumerate(ports)])
    out.open()
    try:
        out.heartbeat()
        assert receive(peers[0], "HEARTBEAT") is not None
        assert peers[0].mav.signing.goodsig_count >= 1
        assert receive(peers[1], "HEARTBEAT", timeout_s=1.0) is None
        assert peers[1].mav.signing.badsig_count >= 1
    finally:
        out.close()
        for peer in peers:
            peer.close()


def test_required_signing_refuses_unsigned_wrongly_signed_and_unknown_messages(key_files):
    key, wrong = (read_signing_key(p) for p in key_files)
    port = free_udp_port()
    out = MavlinkOutput([endpoint(f"udpout:127.0.0.1:{port}", key=key, require=True)])
    seen = []
    out.handlers["GPS_RAW_INT"] = seen.append
    peer = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=1)
    out.open()
    try:
        out.heartbeat()  # the peer learns where we are
        assert receive(peer, "HEARTBEAT") is not None

        def send(signing_key, sats):
            if signing_key is None:
                peer.disable_signing()
            else:
                peer.setup_signing(signing_key, sign_outgoing=True)
            peer.mav.gps_raw_int_send(1, 3, 584300000, 156800000, 60000, 100, 150, 0, 0, sats)

        send(None, 5)
        send(wrong, 6)
        send(key, 7)
        unknown = bytearray(mav.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(peer.mav))
        unknown[7:10] = (0xABCDEF).to_bytes(3, "little")  # a message id no dialect here knows, correctly signed
        peer.write(bytes(unknown))
        stats = lambda: out.link_stats()["endpoints"]["fc"]  # noqa: E731
        settle(out, lambda: sum(v for k, v in stats().items() if k.startswith(("received", "refused"))) >= 4)
        assert [m.satellites_visible for m in seen] == [7]
        s = stats()
        assert (s["received"], s["refused_unsigned"], s["refused_bad_signature"], s["refused_unknown_id"]) == (1, 1, 1, 1)
    finally:
        out.close()
        peer.close()


def test_a_forged_future_timestamp_does_not_lock_out_the_real_sender(key_files):
    """pymavlink's own check stores a stream's timestamp before comparing the signature; ours does not."""
    key, wrong = (read_signing_key(p) for p in key_files)
    sender = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    sender.signing.secret_key, sender.signing.sign_outgoing = key, True
    sender.signing.timestamp = SignatureCheck(key).newest + 10
    forger = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    forger.signing.secret_key, forger.signing.sign_outgoing = wrong, True
    forger.signing.timestamp = 2**47  # far in the future
    check = SignatureCheck(key)
    forged = mav.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(forger)
    real = mav.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(sender)
    assert check.problem(forged, 1, 1) == "bad_signature"
    assert check.problem(real, 1, 1) is None and check.problem(real, 1, 1) == "replayed"
    # Authentic streams only, and at most MAX_STREAMS of them.
    for system in range(200):
        sender.srcSystem = system
        assert check.problem(mav.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(sender), system, 1) is None
    assert check.streams == check.max_streams


# ------------------------------------------------------------------------ serial and TCP links


def test_a_serial_link_frames_the_stream_and_answers_timesync():
    master, slave = pty.openpty()
    out = MavlinkOutput([endpoint(f"{os.ttyname(slave)},115200")])
    out.open()
    try:
        out.publish(make_pose(t_ns=1_000_000_000))
        peer = mav.MAVLink(None, srcSystem=1, srcComponent=1)
        junk = b"\x00\xfd\x07garbage" * 3
        os.write(master, junk + mav.MAVLink_timesync_message(0, 42).pack(peer) + junk)
        settle(out, lambda: out.link_stats()["received"] >= 1)
        data = b""
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline and b"\xfd" not in data[40:]:
            data += os.read(master, 4096)
        msgs = [m for m in mav.MAVLink(None).parse_buffer(data) or []]
        kinds = [m.get_type() for m in msgs]
        assert kinds[:2] == ["ODOMETRY", "TIMESYNC"] and msgs[1].ts1 == 42 and msgs[1].tc1 >= 1_000_000_000
        assert out.link_stats()["endpoints"]["fc"]["bad_bytes"] > 0
    finally:
        out.close()
        os.close(master)
        os.close(slave)


def accept_while_servicing(server: socket.socket, transport, timeout_s: float = 10.0) -> socket.socket:
    """The link's connection, accepted while the link is serviced: it connects from ``service()``, after its
    back-off, so a plain blocking ``accept`` could wait for ever."""
    server.settimeout(0.02)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        transport.service()
        try:
            conn, _ = server.accept()
        except socket.timeout:
            continue
        conn.settimeout(5.0)
        return conn
    raise AssertionError(f"the TCP link did not connect within {timeout_s} s")


def test_a_tcp_link_reconnects_without_blocking():
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    out = MavlinkOutput([endpoint(f"tcp:127.0.0.1:{port}")])
    out.open()
    conn = None
    try:
        ep = out.endpoints[0]
        conn = accept_while_servicing(server, ep.transport)
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline and not ep.transport.connected:
            ep.transport.service()
            time.sleep(0.01)
        out.heartbeat()
        assert mav.MAVLink(None).parse_buffer(conn.recv(4096))[0].get_type() == "HEARTBEAT"
        conn.close()
        started = time.monotonic()
        for _ in range(50):  # the peer is gone: sends fail, the link reopens in the background
            out.heartbeat()
            ep.transport.service()
            out.poll()
            time.sleep(0.01)
        assert time.monotonic() - started < 2.0
        conn = accept_while_servicing(server, ep.transport)
        while not ep.transport.connected and time.monotonic() - started < 10.0:
            ep.transport.service()
            time.sleep(0.05)
        out.heartbeat()
        assert mav.MAVLink(None).parse_buffer(conn.recv(4096))[0].get_type() == "HEARTBEAT"
        assert ep.transport.counts["link_lost"] >= 1
    finally:
        if conn is not None:
            conn.close()
        out.close()
        server.close()


# ------------------------------------------------------------------------------ configuration


def output_from(cfg: dict) -> MavlinkOutput:
    sections = build_sections(cfg)
    return MavlinkOutput.from_section(sections.outputs.mavlink, sections.vehicle.system_id)


def write_key(tmp_path, mode=0o600):
    path = tmp_path / "link.key"
    path.write_bytes(bytes(range(32)))
    path.chmod(mode)
    return path


def test_the_old_single_url_configuration_still_works(tmp_path):
    cfg = load_config(None, {"outputs": {"mavlink": {"enabled": True, "url": "udpout:127.0.0.1:14540",
                                                     "signing_key_file": str(write_key(tmp_path)), "require_signing": True}}})
    out = output_from(cfg)
    (fc,) = out.endpoints
    assert (fc.name, fc.spec.role, fc.spec.rate_hz, fc.inbound.require_signing) == ("flight_controller", "autopilot", 50.0, True)
    assert out.url == "udpout:127.0.0.1:14540"


@pytest.mark.parametrize("mavlink, message", [
    ({"autopilot": "px4", "rate_hz": 100}, r"key 'outputs.mavlink.rate_hz': 100 Hz is outside 30..50 Hz for autopilot px4"),
    ({"autopilot": "ardupilot", "rate_hz": 50}, r"key 'outputs.mavlink.rate_hz'.*EKF3 drops"),
    ({"autopilot": "ardupilot", "endpoints": [{"name": "fc2", "url": "udpout:127.0.0.1:1", "role": "autopilot",
                                               "rate_hz": 45}]}, r"key 'outputs.mavlink.endpoints\[0\].rate_hz'"),
    ({"endpoints": [{"name": "gcs", "url": "udpin:0.0.0.0:99999"}]}, r"key 'outputs.mavlink.endpoints\[0\].url': port"),
    ({"endpoints": [{"name": "gcs", "url": "udpout:h:1", "role": "pilot"}]}, r"endpoints\[0\].role': must be one of"),
    ({"endpoints": [{"name": "gcs", "url": "udpout:h:1", "colour": "red"}]}, r"endpoints\[0\]': unknown key\(s\) \['colour'\]"),
    ({"endpoints": [{"url": "udpout:h:1"}]}, r"endpoints\[0\].name': expected a non-empty string"),
    ({"endpoints": [{"name": "flight_controller", "url": "udpout:h:1"}]}, r"endpoints\[0\].name': 'flight_controller' is used twice"),
    ({"endpoints": [{"name": "g", "url": "udpout:h:1", "require_signing": True}]}, r"endpoints\[0\].require_signing': needs"),
    ({"url": "tcpin:0.0.0.0:5760"}, r"key 'outputs.mavlink.url': 'tcpin:0.0.0.0:5760': tcpin is not served"),
    ({"url": None}, r"key 'outputs.mavlink.url': no link"),
    ({"autopilot": "inav"}, r"key 'outputs.mavlink.autopilot': must be one of px4, ardupilot, generic"),
])
def test_bad_mavlink_settings_are_refused_naming_the_key(mavlink, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, {"outputs": {"mavlink": {"enabled": True, **mavlink}}})


def test_a_world_readable_key_file_is_refused_naming_the_key(tmp_path):
    key = write_key(tmp_path, 0o644)
    with pytest.raises(ConfigError, match=r"key 'outputs.mavlink.signing_key_file': file .* readable or writable by every user"):
        load_config(None, {"outputs": {"mavlink": {"enabled": True, "signing_key_file": str(key)}}})
    endpoints = [{"name": "gcs", "url": "udpout:127.0.0.1:14550", "signing_key_file": str(key)}]
    with pytest.raises(ConfigError, match=r"key 'outputs.mavlink.endpoints\[0\].signing_key_file'"):
        load_config(None, {"outputs": {"mavlink": {"enabled": True, "endpoints": endpoints}}})
    key.chmod(0o640)  # the owner's group may read it (a service group)
    cfg = load_config(None, {"outputs": {"mavlink": {"enabled": True, "endpoints": endpoints}}})
    assert [e.name for e in output_from(cfg).endpoints] == ["flight_controller", "gcs"]


def test_a_flight_controller_of_another_kind_than_configured_is_named(caplog):
    port = free_udp_port()
    fc = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=7, source_component=1)
    out = MavlinkOutput([endpoint(f"udpout:127.0.0.1:{port}", autopilot="px4")], autopilot="px4")
    out.open()
    try:
        out.heartbeat()
        assert receive(fc, "HEARTBEAT") is not None
        fc.mav.heartbeat_send(mav.MAV_TYPE_HELICOPTER, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, mav.MAV_STATE_STANDBY)
        settle(out, lambda: out.link_stats()["received"] >= 1)
        assert out.link_stats()["endpoints"]["fc"]["peer_autopilot"] == "ardupilot"
        assert "says it is ardupilot, but outputs.mavlink.autopilot is px4" in caplog.text
    finally:
        out.close()
        fc.close()
