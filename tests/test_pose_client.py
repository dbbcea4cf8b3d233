"""The mapper's client against a real Zenoh output on loopback: subscribe, pose_at, trajectory, errors."""

import socket
import threading
import time

import numpy as np
import pytest

from vtolpose.estimator.fusion import OutputPose
from vtolpose.estimator.pose_history import PoseHistory
from vtolpose.estimator.core.rotation import quat_from_euler, rotation_angle
from vtolpose.service.outputs.pose_client import PoseClient, PoseUnavailable
from vtolpose.service.outputs.zenoh import ZenohOutput
from vtolpose.service.outputs.zenoh_session import ZenohSettings

MS = 1_000_000
PREFIX = "test/vehicle"
ORIGIN = (58.43, 15.68, 60.0)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def truth(t_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """A turning climb: position quadratic in time (so linear interpolation is not exact), yaw rate 0.5 rad/s."""
    t = t_ns * 1e-9
    return np.array([3.0 * t, 0.2 * t * t, -1.0 * t]), quat_from_euler(0.05, 0.02, 0.5 * t)


def output_pose(t_ns: int) -> OutputPose:
    p, q = truth(t_ns)
    return OutputPose(t_ns, p, np.array([3.0, 0.4 * t_ns * 1e-9, -1.0]), q, np.array([0.0, 0.0, 0.5]),
                      np.eye(9) * 1e-4, np.eye(6) * 1e-4, np.full(3, 1e-6), True, True, 0, t_ns)


@pytest.fixture
def service():
    """A Zenoh output listening on loopback, its history holding 10 s of poses at 100 Hz."""
    port = free_port()
    history, lock = PoseHistory(120.0), threading.Lock()
    for k in range(1, 1001):
        pose = output_pose(k * 10 * MS)
        history.add_fused(pose.t_ns, history.make_row(pose.p, pose.q, pose.v, pose.omega_b, pose.pose_cov))
    out = ZenohOutput(ZenohSettings("peer", [f"tcp/127.0.0.1:{port}"], [], False), PREFIX, history, lock, lambda: ORIGIN)
    out.open()
    yield out, port
    out.close()


@pytest.fixture
def client(service):
    _, port = service
    with PoseClient(PREFIX, connect=[f"tcp/127.0.0.1:{port}"], timeout_s=5.0) as c:
        yield c


def test_pose_at_interpolates_between_estimates(client):
    t = 5_003_700_000  # between the poses at 5.000 and 5.010 s
    pose = client.pose_at(t)
    p0, q0 = truth(5_000_000_000)
    p1, q1 = truth(5_010_000_000)
    alpha = 0.37
    assert pose.t_ns == t and pose.fused and pose.origin == ORIGIN
    assert np.linalg.norm(pose.p - ((1 - alpha) * p0 + alpha * p1)) < 1e-6
    assert np.degrees(rotation_angle(pose.q, truth(t)[1])) < 0.01  # slerp of a constant rate is exact
    assert np.linalg.norm(pose.p - truth(t)[0]) < 1e-3
    assert pose.cov.shape == (6, 6) and pose.cov[0, 0] == pytest.approx(1e-4)


def test_times_outside_the_history_get_an_error_not_a_hang(client):
    for t in (0, 10_000_000_001, -3):
        started = time.monotonic()
        with pytest.raises(PoseUnavailable, match="outside the history"):
            client.pose_at(t)
        assert time.monotonic() - started < 2.0


def test_malformed_parameters_get_an_error(client):
    for selector in (f"{PREFIX}/pose/at?t_ns=soon", f"{PREFIX}/pose/at", f"{PREFIX}/trajectory?from=1"):
        with pytest.raises(PoseUnavailable, match="parameter"):
            client._query(selector)


def test_trajectory_window_and_local_interpolation(client):
    window = client.trajectory(2_003_000_000, 2_103_000_000)  # a 100 ms LIDAR scan, between poses at both ends
    assert window.t_ns.tolist() == list(range(2_000_000_000, 2_110_000_001, 10 * MS))
    returns_t = np.linspace(2_003_000_000, 2_103_000_000, 57).astype(np.int64)
    p, q = window.interpolate(returns_t)
    for t, pk, qk in zip(returns_t, p, q):
        tp, tq = truth(int(t))
        assert np.linalg.norm(pk - tp) < 1e-3 and np.degrees(rotation_angle(qk, tq)) < 0.01
    with pytest.raises(PoseUnavailable, match="does not overlap"):
        client.trajectory(20_000_000_000, 21_000_000_000)


def test_subscribers_receive_every_publication(service, client):
    out, _ = service
    got = []
    client.subscribe(got.append)
    deadline = time.monotonic() + 5.0
    while not got and time.monotonic() < deadline:  # until the subscription has reached the publisher
        out.publish(output_pose(11_000_000_000))
        time.sleep(0.05)
    first_seq = got[-1].seq if got else 0
    for k in range(1, 21):
        out.publish(output_pose(11_000_000_000 + k * 10 * MS))
    deadline = time.monotonic() + 5.0
    while (not got or got[-1].seq < first_seq + 20) and time.monotonic() < deadline:
        time.sleep(0.01)
    last = got[-1]
    assert last.seq == first_seq + 20 and last.t_ns == 11_200_000_000
    assert last.status == "ok" and np.allclose(last.p, truth(11_200_000_000)[0])
    assert [g.seq for g in got[-20:]] == list(range(first_seq + 1, first_seq + 21))


def test_tls_endpoints_from_the_settings(tmp_path):
    """A tls/ endpoint with a CA, certificate and key from the settings (as outputs.zenoh.tls.* give them)."""
    import shutil
    import subprocess

    if shutil.which("openssl") is None:
        pytest.skip("needs the openssl command to make a test certificate")

    def openssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=tmp_path, check=True, capture_output=True)

    openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "1",
            "-subj", "/CN=vtolpose test CA")
    openssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "node.key", "-out", "node.csr", "-subj", "/CN=localhost")
    (tmp_path / "ext.cnf").write_text("subjectAltName=DNS:localhost\nbasicConstraints=CA:FALSE\n")
    openssl("x509", "-req", "-in", "node.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial", "-out", "node.pem",
            "-days", "1", "-extfile", "ext.cnf")
    port = free_port()
    history = PoseHistory(10.0)
    for k in range(1, 11):
        pose = output_pose(k * 10 * MS)
        history.add_fused(pose.t_ns, history.make_row(pose.p, pose.q, pose.v, pose.omega_b, pose.pose_cov))
    ca, cert, key = (str(tmp_path / name) for name in ("ca.pem", "node.pem", "node.key"))
    out = ZenohOutput(ZenohSettings("peer", [f"tls/localhost:{port}"], [], False, ca, cert, key), PREFIX, history,
                      threading.Lock())
    out.open()
    try:
        with PoseClient(PREFIX, settings=ZenohSettings("client", [], [f"tls/localhost:{port}"], False, ca), timeout_s=5.0) as c:
            assert np.allclose(c.pose_at(55 * MS).p, 0.5 * (truth(50 * MS)[0] + truth(60 * MS)[0]))
    finally:
        out.close()
