"""ROS 2 over Zenoh: a replay publishes Odometry and TF as rmw_zenoh does; a separate Zenoh session on
loopback receives them, ``rosbags`` (not our code) decodes the CDR, and frames, covariance and twist
are checked against the JSON pose on ``<prefix>/pose`` of the same instant."""

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore

from vtolpose.config import ConfigError, load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.service.runtime.replay_feed import run_replay

from conftest import free_port

ROS = get_typestore(Stores.ROS2_JAZZY)
ODOM_KEY = f"0/vtol1/odom/nav_msgs::msg::dds_::Odometry_/{ROS.hash_rihs01('nav_msgs/msg/Odometry')}"
TF_KEY = f"0/tf/tf2_msgs::msg::dds_::TFMessage_/{ROS.hash_rihs01('tf2_msgs/msg/TFMessage')}"
# NED -> ENU and FRD -> FLU written out here, independently of vtolpose.estimator.core.frames.
A_ENU_NED = np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])
A_FLU_FRD = np.diag([1.0, -1, -1])


def rot(q_wxyz) -> np.ndarray:
    w, x, y, z = q_wxyz
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


@pytest.fixture(scope="module")
def flight_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("ros2") / "landfill"
    write_flight(simulate_flight("landfill", 20.0, 4), root)
    return root


class Listener:
    """A Zenoh peer on loopback that keeps what a ROS 2 subscriber on rmw_zenoh would see."""

    def __init__(self, port: int) -> None:
        conf = zenoh.Config()
        conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(conf)
        self.lock = threading.Lock()
        self.poses, self.odom, self.tf, self.tokens = {}, [], [], {}
        self.session.declare_subscriber("vtolpose/vtol1/pose", self._pose)
        self.session.declare_subscriber(ODOM_KEY, lambda s: self._ros(self.odom, s))
        self.session.declare_subscriber(TF_KEY, lambda s: self._ros(self.tf, s))
        self.session.liveliness().declare_subscriber("@ros2_lv/0/**", self._token)

    def _pose(self, sample) -> None:
        doc = json.loads(sample.payload.to_string())
        with self.lock:
            self.poses[doc["t_ns"]] = doc

    def _ros(self, into: list, sample) -> None:
        with self.lock:
            into.append((bytes(sample.payload.to_bytes()), bytes(sample.attachment.to_bytes()), str(sample.key_expr)))

    def _token(self, sample) -> None:
        with self.lock:
            self.tokens[str(sample.key_expr)] = sample.kind

    def close(self) -> None:
        self.session.close()


def ros_config(listen: int, connect: int, **ros2) -> dict:
    sets = {"enabled": True, "namespace": "/vtol1", **ros2}
    return load_config(None, {"outputs": {
        "zenoh": {"listen": [f"tcp/127.0.0.1:{listen}"], "connect": [f"tcp/127.0.0.1:{connect}"], "multicast_scouting": False},
        "ros2": sets}})


def run_with_listener(flight_dir: Path, cfg_for) -> "Listener":
    listen_port, runtime_port = free_port(), free_port()
    listener = Listener(listen_port)
    try:
        cfg = cfg_for(runtime_port, listen_port)
        run_replay(Dataset.open(flight_dir), cfg, sensors=["imu", "gps"], speed=10.0, handle_signals=False)
        deadline = time.monotonic() + 5.0  # until the closed output's tokens are withdrawn here too
        while time.monotonic() < deadline and any(k != zenoh.SampleKind.DELETE for k in dict(listener.tokens).values()):
            time.sleep(0.05)
    finally:
        listener.close()
    return listener


@pytest.fixture(scope="module")
def shared(flight_dir) -> Listener:
    """ROS 2 and the JSON output on one session (outputs.zenoh enabled)."""
    def cfg(listen, connect):
        c = ros_config(listen, connect)
        c["outputs.zenoh.enabled"] = True
        return c
    return run_with_listener(flight_dir, cfg)


def test_odometry_matches_the_json_pose_in_rep103_frames(shared):
    assert len(shared.odom) > 500 and len(shared.poses) > 500
    matched = 0
    for payload, _, key in shared.odom[::25]:
        assert key == ODOM_KEY
        msg = ROS.deserialize_cdr(payload, "nav_msgs/msg/Odometry")
        t_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        doc = shared.poses.get(t_ns)
        if doc is None:  # that JSON pose was dropped on the way (congestion control DROP)
            continue
        matched += 1
        assert (msg.header.frame_id, msg.child_frame_id) == ("map", "base_link")
        p_ned, q_ned, v_ned, w_frd = (np.array(doc[k]) for k in ("p", "q", "v", "w"))
        pos = msg.pose.pose.position
        assert np.allclose([pos.x, pos.y, pos.z], A_ENU_NED @ p_ned)
        o = msg.pose.pose.orientation
        assert np.allclose(rot([o.w, o.x, o.y, o.z]), A_ENU_NED @ rot(q_ned) @ A_FLU_FRD.T)
        block = np.kron(np.eye(2), A_ENU_NED)
        cov = np.array(doc["cov"]).reshape(6, 6)
        assert np.allclose(msg.pose.covariance.reshape(6, 6), block @ cov @ block.T)
        lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
        assert np.allclose([lin.x, lin.y, lin.z], A_FLU_FRD @ rot(q_ned).T @ v_ned)
        assert np.allclose([ang.x, ang.y, ang.z], A_FLU_FRD @ w_frd)
        twist_cov = msg.twist.covariance.reshape(6, 6)
        assert np.all(np.linalg.eigvalsh(twist_cov) >= -1e-12) and twist_cov[0, 0] > 0.0
    assert matched > 10


def test_tf_tree_and_attachments(shared):
    odom_by_stamp = {}
    for payload, _, _ in shared.odom:
        msg = ROS.deserialize_cdr(payload, "nav_msgs/msg/Odometry")
        odom_by_stamp[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = msg.pose.pose
    checked = 0
    for payload, _, key in shared.tf[::50]:
        tf = ROS.deserialize_cdr(payload, "tf2_msgs/msg/TFMessage")
        chain = [(t.header.frame_id, t.child_frame_id) for t in tf.transforms]
        assert chain == [("map", "odom"), ("odom", "base_link")]
        identity = tf.transforms[0].transform
        assert (identity.rotation.w, identity.translation.x) == (1.0, 0.0)
        body = tf.transforms[1]
        pose = odom_by_stamp.get((body.header.stamp.sec, body.header.stamp.nanosec))
        if pose is not None:
            checked += 1
            assert (body.transform.translation.x, body.transform.rotation.z) == (pose.position.x, pose.orientation.z)
    assert checked > 5
    for stream in (shared.odom, shared.tf):
        att = [a for _, a, _ in stream]
        seqs = [int.from_bytes(a[0:8], "little", signed=True) for a in att]
        assert seqs == sorted(seqs) and seqs[-1] >= len(seqs) and len(set(seqs)) == len(seqs)
        stamps = np.array([int.from_bytes(a[8:16], "little", signed=True) for a in att])
        assert abs(stamps[-1] * 1e-9 - time.time()) < 60.0  # source time: ns since the UNIX epoch
        assert {a[16] for a in att} == {16} and len({a[17:33] for a in att}) == 1 and all(len(a) == 33 for a in att)
    assert shared.odom[0][1][17:33] != shared.tf[0][1][17:33]  # one GID per publisher


def test_liveliness_tokens_put_the_node_into_the_ros_graph(shared):
    assert len(shared.tokens) == 3
    node = [k for k in shared.tokens if k.split("/")[5] == "NN"]
    pubs = sorted(k for k in shared.tokens if k.split("/")[5] == "MP")
    assert len(node) == 1 and node[0].endswith("/NN/%/%vtol1/vtolpose")
    zid = node[0].split("/")[2]  # the Zenoh session id in hex, as Zenoh writes it (no leading zeros: up to 32 digits)
    assert node[0].startswith("@ros2_lv/0/") and 1 <= len(zid) <= 32 and int(zid, 16) > 0
    odom_hash = ROS.hash_rihs01("nav_msgs/msg/Odometry")
    assert any(p.endswith(f"/MP/%/%vtol1/vtolpose/%vtol1%odom/nav_msgs::msg::dds_::Odometry_/{odom_hash}/::,10:,:,:,,")
               for p in pubs)
    assert any(p.endswith("/MP/%/%vtol1/vtolpose/%tf/tf2_msgs::msg::dds_::TFMessage_/"
                          f"{ROS.hash_rihs01('tf2_msgs/msg/TFMessage')}/::,100:,:,:,,") for p in pubs)
    # gone again when the output closed (DELETE seen last for every token)
    assert {str(kind) for kind in shared.tokens.values()} == {str(zenoh.SampleKind.DELETE)}


def test_own_session_without_the_json_output(flight_dir):
    """Only outputs.ros2: it opens its own session with the outputs.zenoh settings; no odom frame asked."""
    got = run_with_listener(flight_dir, lambda listen, connect: ros_config(listen, connect, odom_frame=None))
    assert not got.poses and len(got.odom) > 500
    tf = ROS.deserialize_cdr(got.tf[-1][0], "tf2_msgs/msg/TFMessage")
    assert [(t.header.frame_id, t.child_frame_id) for t in tf.transforms] == [("map", "base_link")]


@pytest.mark.parametrize("key, value", [("namespace", "/9lives"), ("node_name", "a/b"), ("odometry_topic", "odom//x"),
                                        ("base_frame", "base link")])
def test_bad_ros_names_refuse_to_start(flight_dir, key, value):
    cfg = ros_config(free_port(), free_port(), **{key: value})
    with pytest.raises(ConfigError, match=f"outputs.ros2.{key}"):
        run_replay(Dataset.open(flight_dir), cfg, sensors=["imu", "gps"], speed=0.0, handle_signals=False)
