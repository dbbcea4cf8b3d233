"""The ROS 2 wire form checked against fixed values and readers that are not the project's own.

Everything ``rosbags`` does for the bridge (CDR, type hashes) is checked here without it: the
expected CDR is written by a small writer in this file, decoded by a small reader in this file, the
attachment is read by zenoh-ext's deserialiser, the RIHS01 hashes and GIDs are literal strings,
and QoS fields are parsed the way rmw_zenoh's ``keyexpr_to_qos`` (``liveliness_utils.cpp``) does.
"""

from __future__ import annotations

import logging
import struct
import time

import numpy as np
import pytest
import zenoh
import zenoh.ext

from vtolpose.config import ConfigError, load_config
from vtolpose.config.sections import Ros2Section, build_sections
from vtolpose.service.outputs import ros2_msgs
from vtolpose.service.outputs.ros2 import (
    LEGACY_ATTACHMENT, Ros2Names, Ros2Output, attachment, gid_of, qos_field,
)
from vtolpose.service.outputs.zenoh_session import ZenohSettings

from test_mavlink_out import make_pose
from test_ros2 import free_port

# REP 2016 hashes of the Jazzy (and Rolling) definitions, as rmw_zenoh puts them in key expressions.
ODOMETRY_HASH = "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"
TF_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
# XXH3-128("abc") is 0x06b05ab6733a6185_78af5f94892f3950 (xxHash's test vectors); rmw_zenoh copies the
# low 64 bits, then the high 64 bits, each in the machine's (little-endian) order.
GID_OF_ABC = bytes.fromhex("50392f89945faf78" "85613a73b65ab006")
# rmw_zenoh's own default profile (qos.cpp): what an empty QoS field stands for.
RMW_ZENOH_DEFAULTS = {"reliability": 1, "durability": 2, "history": 1, "depth": 42}


def parse_qos(field: str) -> dict[str, int]:
    """rmw_zenoh's ``keyexpr_to_qos``: six ':' parts; history, deadline and lifespan split by ',' into two,
    liveliness into three; an empty entry is the default profile's; None when the field is malformed."""
    parts = field.split(":")
    if len(parts) < 6:
        raise ValueError("fewer than 6 parts")
    history, deadline, lifespan, liveliness = (p.split(",") for p in parts[2:6])
    if len(history) < 2 or len(deadline) < 2 or len(lifespan) < 2 or len(liveliness) < 3:
        raise ValueError("a part has too few components")

    def number(text: str, default: int) -> int:
        if text == "":
            return default
        if not text.isdigit():
            raise ValueError(f"non-numeric {text!r}")
        return int(text)

    return {"reliability": number(parts[0], RMW_ZENOH_DEFAULTS["reliability"]),
            "durability": number(parts[1], RMW_ZENOH_DEFAULTS["durability"]),
            "history": number(history[0], RMW_ZENOH_DEFAULTS["history"]),
            "depth": number(history[1], RMW_ZENOH_DEFAULTS["depth"])}


class CdrWriter:
    """Little-endian CDR with the encapsulation header; alignment counted from after the header."""

    def __init__(self) -> None:
        self.body = bytearray()

    def _align(self, n: int) -> None:
        self.body += b"\0" * ((-len(self.body)) % n)

    def put(self, fmt: str, *values) -> "CdrWriter":
        self._align(struct.calcsize(fmt[-1]))
        self.body += struct.pack("<" + fmt, *values)
        return self

    def string(self, text: str) -> "CdrWriter":
        data = text.encode() + b"\0"
        return self.put("I", len(data)).raw(data)

    def raw(self, data: bytes) -> "CdrWriter":
        self.body += data
        return self

    def bytes(self) -> bytes:
        return b"\x00\x01\x00\x00" + bytes(self.body)


class CdrReader:
    def __init__(self, data: bytes) -> None:
        assert data[:4] == b"\x00\x01\x00\x00", "CDR little-endian encapsulation"
        self.body, self.i = data[4:], 0

    def get(self, fmt: str) -> tuple:
        size = struct.calcsize(fmt[-1])
        self.i += (-self.i) % size
        values = struct.unpack_from("<" + fmt, self.body, self.i)
        self.i += struct.calcsize("<" + fmt)
        return values

    def string(self) -> str:
        (n,) = self.get("I")
        text = self.body[self.i:self.i + n]
        self.i += n
        assert text.endswith(b"\0")
        return text[:-1].decode()

    def done(self) -> bool:
        return self.i == len(self.body)


def fixed_ros_pose() -> ros2_msgs.RosPose:
    cov = np.arange(36, dtype=float).reshape(6, 6) * 1e-3
    return ros2_msgs.RosPose(1_700_000_000_123_456_789, np.array([1.5, -2.25, 3.0]), np.array([0.5, 0.5, -0.5, 0.5]),
                             cov, np.array([0.1, 0.2, 0.3]), np.array([-0.01, 0.02, -0.03]), cov.T.copy())


def test_odometry_cdr_is_the_bytes_written_by_hand_and_reads_back():
    pose = fixed_ros_pose()
    ours = ros2_msgs.serialize(ros2_msgs.odometry(pose, ros2_msgs.RosFrames()), ros2_msgs.ODOMETRY)
    expected = (CdrWriter().put("iI", 1_700_000_000, 123_456_789).string("map").string("base_link")
                .put("3d", 1.5, -2.25, 3.0).put("4d", 0.5, -0.5, 0.5, 0.5)  # x y z; quaternion x y z w
                .put("36d", *pose.pose_cov.ravel()).put("3d", 0.1, 0.2, 0.3).put("3d", -0.01, 0.02, -0.03)
                .put("36d", *pose.twist_cov.ravel()).bytes())
    assert ours == expected
    r = CdrReader(ours)
    assert r.get("iI") == (1_700_000_000, 123_456_789) and r.string() == "map" and r.string() == "base_link"
    assert r.get("7d") == (1.5, -2.25, 3.0, 0.5, -0.5, 0.5, 0.5)
    assert np.array_equal(r.get("36d"), pose.pose_cov.ravel())
    assert r.get("6d") == (0.1, 0.2, 0.3, -0.01, 0.02, -0.03)
    assert np.array_equal(r.get("36d"), pose.twist_cov.ravel()) and r.done()


# map -> odom (identity) and odom -> base_link of fixed_ros_pose(), as a TFMessage.
TF_CDR = bytes.fromhex(
    "0001000002000000"
    "00f1536515cd5b07040000006d617000050000006f646f6d00000000"
    "000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000f03f"
    "00f1536515cd5b07050000006f646f6d000000000a000000626173655f6c696e6b00000000000000"
    "000000000000f83f00000000000002c00000000000000840000000000000e03f000000000000e0bf000000000000e03f000000000000e03f")


def test_tf_message_cdr_is_the_fixed_bytes():
    ours = ros2_msgs.serialize(ros2_msgs.transforms(fixed_ros_pose(), ros2_msgs.RosFrames()), ros2_msgs.TF_MESSAGE)
    assert ours == TF_CDR
    r = CdrReader(ours)
    assert r.get("I") == (2,)
    assert r.get("iI") == (1_700_000_000, 123_456_789) and (r.string(), r.string()) == ("map", "odom")
    assert r.get("7d") == (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    assert r.get("iI") == (1_700_000_000, 123_456_789) and (r.string(), r.string()) == ("odom", "base_link")
    assert r.get("7d") == (1.5, -2.25, 3.0, 0.5, -0.5, 0.5, 0.5) and r.done()


def test_type_hashes_gid_and_attachment_are_rmw_zenohs():
    assert ros2_msgs.type_hash(ros2_msgs.ODOMETRY) == ODOMETRY_HASH
    assert ros2_msgs.type_hash(ros2_msgs.TF_MESSAGE) == TF_HASH
    assert gid_of("abc") == GID_OF_ABC
    token = ("@ros2_lv/0/1a2b3c/0/1/MP/%/%/vtolpose/%odom/nav_msgs::msg::dds_::Odometry_/"
             f"{ODOMETRY_HASH}/::,10:,:,:,,")
    assert gid_of(token) == bytes.fromhex("74e2ea05261b3f19af1e76dda1606204")
    att = attachment(7, 1_700_000_000_123_456_789, GID_OF_ABC)
    assert att == bytes.fromhex("0700000000000000" "15cd853dfe9c9717" "10" "50392f89945faf7885613a73b65ab006")
    seq, stamp, gid = zenoh.ext.z_deserialize(tuple[zenoh.ext.Int64, zenoh.ext.Int64, bytes], zenoh.ZBytes(att))
    assert (seq, stamp, gid) == (7, 1_700_000_000_123_456_789, GID_OF_ABC)
    assert not att.startswith(LEGACY_ATTACHMENT)
    legacy = bytes(zenoh.ext.z_serialize(("sequence_number", zenoh.ext.Int64(7))))
    assert legacy.startswith(LEGACY_ATTACHMENT)  # what an rmw_zenoh 0.2.0-0.2.3 node writes first


def names(**ros2) -> Ros2Names:
    cfg = load_config(None, {"outputs": {"ros2": {"enabled": True, **ros2}}})
    return Ros2Names.from_section(build_sections(cfg).outputs.ros2)


def test_qos_fields_read_back_as_meant_by_rmw_zenohs_parser():
    assert parse_qos(qos_field(10)) == {**RMW_ZENOH_DEFAULTS, "depth": 10}
    assert parse_qos(qos_field(100))["depth"] == 100
    assert parse_qos("::,:,:,:,,")["depth"] == 42  # a depth left out is rmw_zenoh's default, not ROS's 10
    token = names().publisher_token("1a2b", 1, "/odom", ros2_msgs.ODOMETRY, 10)
    assert token.split("/")[-1] == "::,10:,:,:,," and parse_qos(token.split("/")[-1])["depth"] == 10


@pytest.mark.parametrize("topic", ["odom/", "/odom/", "a//b", "/"])
def test_a_topic_ending_in_a_slash_is_refused(topic):
    with pytest.raises(ConfigError, match=r"outputs.ros2.odometry_topic.*not a ROS 2 name"):
        names(odometry_topic=topic)


def test_topic_names_agree_between_key_and_token():
    n = names(namespace="/vtol1", odometry_topic="nav/odom")
    assert n.odometry_topic == "/vtol1/nav/odom"
    assert n.topic_key(n.odometry_topic, ros2_msgs.ODOMETRY).startswith("0/vtol1/nav/odom/nav_msgs::msg::dds_::Odometry_/")
    assert "/%vtol1%nav%odom/" in n.publisher_token("z", 1, n.odometry_topic, ros2_msgs.ODOMETRY, 10)


def output_config(port: int, stamp: str) -> Ros2Section:
    cfg = load_config(None, {"outputs": {"zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]},
                                         "ros2": {"enabled": True, "stamp": stamp}}})
    return build_sections(cfg).outputs.ros2


class Receiver:
    """A Zenoh peer that takes vtolpose's Odometry and decodes its stamp with the reader above."""

    def __init__(self, port: int) -> None:
        conf = zenoh.Config()
        conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
        conf.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(conf)
        self.stamps: list[int] = []
        self.session.declare_subscriber(f"0/odom/nav_msgs::msg::dds_::Odometry_/{ODOMETRY_HASH}", self._odom)

    def _odom(self, sample) -> None:
        sec, nanosec = CdrReader(bytes(sample.payload.to_bytes())).get("iI")
        self.stamps.append(sec * 1_000_000_000 + nanosec)


@pytest.mark.parametrize("live, stamp, clock", [(True, "auto", "system"), (False, "auto", "data"),
                                                 (False, "system", "system"), (True, "estimator", "monotonic")])
def test_stamps_are_on_the_clock_asked_for(live, stamp, clock):
    port = free_port()
    out = Ros2Output(output_config(port, stamp), ZenohSettings("peer", [f"tcp/127.0.0.1:{port}"]), live=live)
    out.open()
    receiver = Receiver(port)
    try:
        time.sleep(0.5)
        data_t0 = 5_000_000_000  # a replay's clock: 5 s into the data
        for k in range(20):
            now = time.monotonic_ns() if live else data_t0 + k * 10_000_000
            out.publish(make_pose(t_ns=now))
            time.sleep(0.01)
        time.sleep(0.3)
    finally:
        receiver.session.close()
        out.close()
    assert len(receiver.stamps) >= 15
    reference = {"system": time.time_ns(), "monotonic": time.monotonic_ns(), "data": data_t0 + 200_000_000}[clock]
    assert abs(receiver.stamps[-1] - reference) < 1_000_000_000, (clock, receiver.stamps[-1] - reference)
    if clock == "data":
        assert receiver.stamps[0] == data_t0


def test_a_ros_node_on_an_old_rmw_zenoh_is_reported(caplog):
    port = free_port()
    out = Ros2Output(output_config(port, "auto"), ZenohSettings("peer", [f"tcp/127.0.0.1:{port}"]))
    out.open()
    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    old_node = zenoh.open(conf)
    legacy = zenoh.ext.z_serialize(("sequence_number", zenoh.ext.Int64(1), "source_timestamp", zenoh.ext.Int64(2),
                                    "source_gid", bytes(16)))
    try:
        with caplog.at_level(logging.WARNING):
            time.sleep(0.5)
            key = "0/rosout/rcl_interfaces::msg::dds_::Log_/RIHS01_0"
            old_node.put(key, b"\x00\x01\x00\x00", attachment=attachment(1, 2, bytes(16)))  # a current node: nothing said
            time.sleep(0.3)
            assert "legacy_rmw_zenoh_sessions" not in out.stats
            old_node.put(key, b"\x00\x01\x00\x00", attachment=legacy)
            deadline = time.monotonic() + 3.0
            while "legacy_rmw_zenoh_sessions" not in out.stats and time.monotonic() < deadline:
                time.sleep(0.05)
    finally:
        old_node.close()
        out.close()
    assert out.stats["legacy_rmw_zenoh_sessions"] == 1
    assert "runs rmw_zenoh 0.2.0-0.2.3" in caplog.text and ">= 0.2.4" in caplog.text
