"""ROS 2 without ROS: ``nav_msgs/Odometry`` and ``tf2_msgs/TFMessage`` over Zenoh as rmw_zenoh sends them.

A ROS 2 node running on ``rmw_zenoh_cpp`` subscribes to these topics with no bridge. What makes
a Zenoh publication a ROS 2 message, per rmw_zenoh's design document (``docs/design.md`` of
ros2/rmw_zenoh at commit 99a6a2bd: the zenoh 1.x design with REP 2016 type hashes):

- key expression ``<domain_id>/<topic without its leading slash>/<DDS type name>/<type hash>``,
  e.g. ``0/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_…``;
- payload: the message in CDR (little-endian, with its 4-byte encapsulation header);
- attachment: sequence number (int64 LE, from 1), source time (int64 LE, ns since the UNIX
  epoch), then the publisher's GID as one length byte (16) and 16 bytes;
- liveliness tokens that put the node and each publisher into the ROS graph:
  ``@ros2_lv/<domain>/<zenoh session id>/<node id>/<node id>/NN/<enclave>/<namespace>/<node>`` and
  ``@ros2_lv/<domain>/<session id>/<node id>/<entity id>/MP/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>``,
  where names have every ``/`` replaced by ``%`` (an empty one is ``%``) and the QoS field lists
  only what differs from ROS's default profile (reliable, volatile, keep-last 10).

The design leaves the GID's derivation to the implementation; ours is a 16-byte BLAKE2b of the
publisher's token, stable for a session. Publications use congestion control DROP (rmw_zenoh's
choice for keep-last history), so a slow ROS node never delays the pose. The Zenoh session is
the ``outputs.zenoh`` one when that output is on (one session per process, as rmw_zenoh has one
per context), else a session of its own with the same settings.
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import re
import struct
import time
from dataclasses import dataclass
from typing import Any, Callable

import zenoh

from vtolpose.config import ConfigError
from vtolpose.estimator.fusion import OutputPose
from vtolpose.service.outputs import ros2_msgs
from vtolpose.service.outputs.zenoh_session import ZenohSettings

log = logging.getLogger(__name__)

ADMIN_SPACE = "@ros2_lv"
DEFAULT_DEPTH = 10  # ROS's default QoS history depth
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def dds_type_name(typename: str) -> str:
    """``nav_msgs/msg/Odometry`` → ``nav_msgs::msg::dds_::Odometry_`` (the type name as DDS declares it)."""
    package, kind, name = typename.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    return name.replace("/", "%") or "%"


def qos_field(depth: int) -> str:
    """rmw_zenoh's compact QoS: reliability:durability:history,depth:deadline:lifespan:liveliness, defaults empty."""
    return f"::,{'' if depth == DEFAULT_DEPTH else depth}:,:,:,,"


def attachment(seq: int, t_ns: int, gid: bytes) -> bytes:
    return struct.pack("<qqB16s", seq, t_ns, len(gid), gid)


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """``(sequence number, source time ns, GID)`` of an rmw_zenoh attachment."""
    seq, t_ns, n = struct.unpack_from("<qqB", data)
    return seq, t_ns, bytes(data[17:17 + n])


def _check_name(key: str, name: str, allow_slash: bool, allow_empty: bool = False) -> str:
    """``name`` if it is a ROS 2 name (tokens of letters, digits and underscores, not starting with a
    digit; with ``allow_slash``, tokens joined by single slashes), else ConfigError naming ``key``."""
    parts = name.strip("/").split("/") if allow_slash else [name]
    if name.strip("/") == "" and allow_empty and allow_slash:
        return name
    if not all(_NAME.match(p) for p in parts):
        raise ConfigError(f"key '{key}': {name!r} is not a ROS 2 name (letters, digits, underscores"
                          f"{', / between tokens' if allow_slash else ''}; not starting with a digit)")
    return name


@dataclass(frozen=True, slots=True)
class Ros2Names:
    """Domain, node and topics (``outputs.ros2.*``), checked as ROS 2 names."""

    domain_id: int
    namespace: str  # "/" or "/a/b"
    node: str
    odometry_topic: str  # fully qualified
    tf_topic: str

    @classmethod
    def from_config(cls, cfg: dict[str, Any]) -> "Ros2Names":
        ns = _check_name("outputs.ros2.namespace", cfg["outputs.ros2.namespace"], True, allow_empty=True).strip("/")
        namespace = f"/{ns}" if ns else "/"

        def qualified(key: str) -> str:
            name = _check_name(key, cfg[key], True)
            return name if name.startswith("/") else f"{namespace.rstrip('/')}/{name}"

        return cls(cfg["outputs.ros2.domain_id"], namespace, _check_name("outputs.ros2.node_name", cfg["outputs.ros2.node_name"], False),
                   qualified("outputs.ros2.odometry_topic"), qualified("outputs.ros2.tf_topic"))

    def topic_key(self, topic: str, typename: str) -> str:
        return f"{self.domain_id}/{topic.strip('/')}/{dds_type_name(typename)}/{ros2_msgs.type_hash(typename)}"

    def node_token(self, zid: str, node_id: int = 0) -> str:
        return f"{ADMIN_SPACE}/{self.domain_id}/{zid}/{node_id}/{node_id}/NN/%/{mangle(self.namespace)}/{self.node}"

    def publisher_token(self, zid: str, entity_id: int, topic: str, typename: str, depth: int, node_id: int = 0) -> str:
        return (f"{ADMIN_SPACE}/{self.domain_id}/{zid}/{node_id}/{entity_id}/MP/%/{mangle(self.namespace)}/{self.node}/"
                f"{mangle(topic)}/{dds_type_name(typename)}/{ros2_msgs.type_hash(typename)}/{qos_field(depth)}")


class _RosPublisher:
    """One rmw_zenoh-style publisher: Zenoh publisher, liveliness token, GID and sequence numbers."""

    def __init__(self, session: zenoh.Session, names: Ros2Names, entity_id: int, topic: str, typename: str,
                 depth: int) -> None:
        token = names.publisher_token(str(session.zid()), entity_id, topic, typename, depth)
        self.gid = hashlib.blake2b(token.encode(), digest_size=16).digest()
        self.key = names.topic_key(topic, typename)
        self.typename = typename
        self.seq = 0
        self.publisher = session.declare_publisher(self.key, congestion_control=zenoh.CongestionControl.DROP)
        self.token = session.liveliness().declare_token(token)

    def put(self, msg: object) -> None:
        self.seq += 1
        self.publisher.put(ros2_msgs.serialize(msg, self.typename), attachment=attachment(self.seq, time.time_ns(), self.gid))

    def undeclare(self) -> None:
        for entity in (self.token, self.publisher):
            try:
                entity.undeclare()
            except zenoh.ZError as exc:  # the session is closing anyway
                log.debug("ROS 2 publisher undeclare on close: %s", exc)


class Ros2Output:
    """Odometry and TF for ROS 2 nodes on rmw_zenoh, at every estimate (see the module docstring)."""

    name = "ros2"

    def __init__(self, cfg: dict[str, Any], settings: ZenohSettings,
                 shared_session: Callable[[], zenoh.Session | None] = lambda: None) -> None:
        self.names = Ros2Names.from_config(cfg)
        self.frames = ros2_msgs.RosFrames(
            _check_name("outputs.ros2.map_frame", cfg["outputs.ros2.map_frame"], False),
            None if cfg["outputs.ros2.odom_frame"] is None else _check_name("outputs.ros2.odom_frame", cfg["outputs.ros2.odom_frame"], False),
            _check_name("outputs.ros2.base_frame", cfg["outputs.ros2.base_frame"], False))
        self.system_stamps = cfg["outputs.ros2.stamp"] == "system"
        self.settings = settings
        self.shared_session = shared_session
        self.session: zenoh.Session | None = None
        self._own_session = False
        self._stamp_offset_ns = 0
        self._node_token: Any = None
        self._odom: _RosPublisher | None = None
        self._tf: _RosPublisher | None = None
        self.stats = {"odometry_published": 0, "tf_published": 0}

    def open(self) -> None:
        session = self.shared_session()
        self._own_session = session is None
        self.session = session = zenoh.open(self.settings.to_zenoh()) if session is None else session
        # Live stamps are the monotonic clock; "system" moves them onto the system clock ROS nodes use.
        self._stamp_offset_ns = time.time_ns() - time.monotonic_ns() if self.system_stamps else 0
        self._node_token = session.liveliness().declare_token(self.names.node_token(str(session.zid())))
        self._odom = _RosPublisher(session, self.names, 1, self.names.odometry_topic, ros2_msgs.ODOMETRY, DEFAULT_DEPTH)
        self._tf = _RosPublisher(session, self.names, 2, self.names.tf_topic, ros2_msgs.TF_MESSAGE, 100)
        log.info("ROS 2 (rmw_zenoh) node %s%s in domain %d: %s, %s", self.names.namespace.rstrip("/") + "/", self.names.node,
                 self.names.domain_id, self.names.odometry_topic, self.names.tf_topic)

    def publish(self, pose: OutputPose) -> None:
        if self._odom is None or self._tf is None or not pose.position_initialized:
            return
        ros = ros2_msgs.ros_pose(pose, pose.t_ns + self._stamp_offset_ns)
        self._odom.put(ros2_msgs.odometry(ros, self.frames))
        self.stats["odometry_published"] += 1
        self._tf.put(ros2_msgs.transforms(ros, self.frames))
        self.stats["tf_published"] += 1

    def publish_status(self, status: dict[str, Any]) -> None:
        """The status goes out on ``<prefix>/status`` (Zenoh output) and to Foxglove; ROS gets poses only."""

    async def serve(self, stop: asyncio.Event) -> None:
        await stop.wait()

    def close(self) -> None:
        for pub in (self._tf, self._odom):
            if pub is not None:
                pub.undeclare()
        self._tf = self._odom = None
        if self._node_token is not None:
            try:
                self._node_token.undeclare()
            except zenoh.ZError as exc:
                log.debug("ROS 2 node token undeclare on close: %s", exc)
            self._node_token = None
        if self.session is not None and self._own_session:
            self.session.close()
        self.session = None
