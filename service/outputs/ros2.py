"""ROS 2 without ROS: ``nav_msgs/Odometry`` and ``tf2_msgs/TFMessage`` over Zenoh as rmw_zenoh sends them.

A ROS 2 node running on ``rmw_zenoh_cpp`` (Jazzy 0.2.4 or later, Rolling 0.6.0 or later) subscribes
to these topics with no bridge. What makes a Zenoh publication a ROS 2 message, per rmw_zenoh's
design document and its ``liveliness_utils.cpp`` and ``qos.cpp`` (docs/interop.md has the details):

- key expression ``<domain_id>/<topic without its leading slash>/<DDS type name>/<type hash>``,
  e.g. ``0/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_…``;
- payload: the message in CDR (little-endian, with its 4-byte encapsulation header);
- attachment, 33 bytes: sequence number (int64 LE, from 1), source time (int64 LE, ns since the
  UNIX epoch), then the publisher's GID as one length byte (16) and 16 bytes. Jazzy 0.2.0-0.2.3
  wrote (and expect) named fields instead and throw on ours: such a node is recognised by its own
  publications and reported (:data:`LEGACY_ATTACHMENT`);
- liveliness tokens that put the node and each publisher into the ROS graph:
  ``@ros2_lv/<domain>/<zenoh session id>/<node id>/<node id>/NN/<enclave>/<namespace>/<node>`` and
  ``@ros2_lv/<domain>/<session id>/<node id>/<entity id>/MP/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>``,
  where names have every ``/`` replaced by ``%`` (an empty one is ``%``) and the QoS field leaves
  out only what equals rmw_zenoh's own default profile (reliable, volatile, keep-last *42*,
  infinite deadline, lifespan and lease), so a depth of 10 is written;
- the GID: rmw_zenoh's, XXH3-128 of the publisher's token, its low 64 bits then its high 64 bits,
  each little-endian, so ``message_info.publisher_gid`` matches the graph's.

Publications use congestion control DROP (rmw_zenoh's choice for keep-last history), so a slow ROS
node never delays the pose. The Zenoh session is the ``outputs.zenoh`` one when that output is on
(one session per process, as rmw_zenoh has one per context), else a session of its own with the same
settings. rmw_zenohd's router does not forward between its peers: the session reaches ROS nodes as a
client of the router (``outputs.zenoh.mode: client``), or as a peer with gossip on; a peer that
connects with gossip off is warned about at start.
"""

from __future__ import annotations

import asyncio
import logging
import re
import struct
import time
from dataclasses import dataclass
from typing import Any, Callable

import xxhash
import zenoh

from vtolpose.config import ConfigError
from vtolpose.config.sections import Ros2Section
from vtolpose.estimator import OutputPose
from vtolpose.service.outputs import ros2_msgs
from vtolpose.service.outputs.zenoh_session import ZenohSettings

log = logging.getLogger(__name__)

ADMIN_SPACE = "@ros2_lv"
DEFAULT_DEPTH = 10  # ROS's default QoS history depth, /odom's
TF_DEPTH = 100
RMW_ZENOH_DEFAULT_DEPTH = 42  # what rmw_zenoh reads an empty depth field as (its qos.cpp)
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
# The first bytes of an rmw_zenoh 0.2.0-0.2.3 attachment: the field name "sequence_number", length-prefixed.
LEGACY_ATTACHMENT = b"\x0fsequence_number"
# Topics every rclcpp/rclpy node publishes on soon after it starts: where an old rmw_zenoh shows itself.
_WATCHED_TOPICS = ("rosout", "parameter_events")


def dds_type_name(typename: str) -> str:
    """``nav_msgs/msg/Odometry`` → ``nav_msgs::msg::dds_::Odometry_`` (the type name as DDS declares it)."""
    package, kind, name = typename.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    return name.replace("/", "%") or "%"


def qos_field(depth: int) -> str:
    """rmw_zenoh's compact QoS of a reliable, volatile, keep-last ``depth`` publisher:
    ``reliability:durability:history,depth:deadline s,ns:lifespan s,ns:liveliness,lease s,ns``, where a
    field equal to rmw_zenoh's default profile is left empty (its default depth is 42, not ROS's 10)."""
    return f"::,{'' if depth == RMW_ZENOH_DEFAULT_DEPTH else depth}:,:,:,,"


def gid_of(token: str) -> bytes:
    """rmw_zenoh's GID of an entity: XXH3-128 of its liveliness token, low 64 bits first, both little-endian."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")


def attachment(seq: int, t_ns: int, gid: bytes) -> bytes:
    return struct.pack("<qqB16s", seq, t_ns, len(gid), gid)


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """``(sequence number, source time ns, GID)`` of an rmw_zenoh attachment."""
    seq, t_ns, n = struct.unpack_from("<qqB", data)
    return seq, t_ns, bytes(data[17:17 + n])


def _check_name(key: str, name: str, allow_slash: bool, allow_empty: bool = False) -> str:
    """``name`` if it is a ROS 2 name (tokens of letters, digits and underscores, not starting with a
    digit; with ``allow_slash``, tokens joined by single slashes, optionally after one leading slash,
    never ending in one), else ConfigError naming ``key``. ``allow_empty``: "/" too (the root namespace)."""
    if allow_slash and allow_empty and name == "/":
        return name
    parts = (name[1:] if name.startswith("/") else name).split("/") if allow_slash else [name]
    if not all(_NAME.match(p) for p in parts):
        ending = "; no / at the end" if allow_slash and name.endswith("/") else ""
        raise ConfigError(f"key '{key}': {name!r} is not a ROS 2 name (letters, digits, underscores"
                          f"{', / between tokens' if allow_slash else ''}; not starting with a digit{ending})")
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
    def from_section(cls, ros2: Ros2Section) -> "Ros2Names":
        ns = _check_name("outputs.ros2.namespace", ros2.namespace, True, allow_empty=True).strip("/")
        namespace = f"/{ns}" if ns else "/"

        def qualified(key: str, name: str) -> str:
            name = _check_name(key, name, True)
            return name if name.startswith("/") else f"{namespace.rstrip('/')}/{name}"

        return cls(ros2.domain_id, namespace, _check_name("outputs.ros2.node_name", ros2.node_name, False),
                   qualified("outputs.ros2.odometry_topic", ros2.odometry_topic),
                   qualified("outputs.ros2.tf_topic", ros2.tf_topic))

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
        self.gid = gid_of(token)
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
    """Odometry and TF for ROS 2 nodes on rmw_zenoh, at every estimate (see the module docstring).

    Stamps (``outputs.ros2.stamp``): ``estimator``, the pose's own time; ``system``, the system clock
    ROS nodes use (live: the monotonic IMU stamps moved by the offset between the two clocks; a
    replay: the data's time moved so that its first pose is stamped when it is published); ``auto``
    (the default): ``system`` live, ``estimator`` in a replay (``live``).
    """

    name = "ros2"

    def __init__(self, ros2: Ros2Section, settings: ZenohSettings,
                 shared_session: Callable[[], zenoh.Session | None] = lambda: None, live: bool = False) -> None:
        self.names = Ros2Names.from_section(ros2)
        self.frames = ros2_msgs.RosFrames(
            _check_name("outputs.ros2.map_frame", ros2.map_frame, False),
            None if ros2.odom_frame is None else _check_name("outputs.ros2.odom_frame", ros2.odom_frame, False),
            _check_name("outputs.ros2.base_frame", ros2.base_frame, False))
        stamp = ros2.stamp
        self.system_stamps = stamp == "system" or (stamp == "auto" and live)
        self.live = live
        self.settings = settings
        self.shared_session = shared_session
        self.session: zenoh.Session | None = None
        self._own_session = False
        self._stamp_offset_ns: int | None = 0
        self._node_token: Any = None
        self._odom: _RosPublisher | None = None
        self._tf: _RosPublisher | None = None
        self._watchers: list[Any] = []
        self.legacy_sessions: set[str] = set()
        self.stats: dict[str, Any] = {"odometry_published": 0, "tf_published": 0, "stamps": "system" if self.system_stamps else "estimator"}

    def open(self) -> None:
        session = self.shared_session()
        self._own_session = session is None
        if self.settings.mode == "peer" and self.settings.connect and not self.settings.multicast_scouting:
            log.warning("outputs.ros2: a Zenoh peer with gossip off, connecting to %s. rmw_zenohd (the ROS 2 router) does "
                        "not forward between its peers, so ROS 2 nodes will not see vtolpose unless they connect to it "
                        "themselves: set outputs.zenoh.mode: client to go through the router (docs/interop.md)",
                        ", ".join(self.settings.connect))
        self.session = session = zenoh.open(self.settings.to_zenoh()) if session is None else session
        if not self.system_stamps:
            self._stamp_offset_ns = 0
        elif self.live:  # live stamps are on the monotonic clock: the offset between the two clocks
            self._stamp_offset_ns = time.time_ns() - time.monotonic_ns()
        else:  # a replay's clock is the data's: measured at the first pose
            self._stamp_offset_ns = None
        self._node_token = session.liveliness().declare_token(self.names.node_token(str(session.zid())))
        self._odom = _RosPublisher(session, self.names, 1, self.names.odometry_topic, ros2_msgs.ODOMETRY, DEFAULT_DEPTH)
        self._tf = _RosPublisher(session, self.names, 2, self.names.tf_topic, ros2_msgs.TF_MESSAGE, TF_DEPTH)
        self._watchers = [session.declare_subscriber(f"{self.names.domain_id}/{topic}/**", self._check_attachment)
                          for topic in _WATCHED_TOPICS]
        log.info("ROS 2 (rmw_zenoh >= 0.2.4 on Jazzy, >= 0.6.0 on Rolling) node %s%s in domain %d: %s, %s; stamps on the %s "
                 "clock", self.names.namespace.rstrip("/") + "/", self.names.node, self.names.domain_id,
                 self.names.odometry_topic, self.names.tf_topic, "system" if self.system_stamps else "data's")

    def _check_attachment(self, sample: zenoh.Sample) -> None:
        """On a Zenoh thread: a ROS node's own publication; one from rmw_zenoh 0.2.0-0.2.3 is reported once."""
        attachment = sample.attachment
        if attachment is None or not bytes(attachment.to_bytes()).startswith(LEGACY_ATTACHMENT):
            return
        source = sample.source_info.source_id if sample.source_info is not None else None
        who = str(source.zid) if source is not None else str(sample.key_expr)
        if who not in self.legacy_sessions:
            self.legacy_sessions.add(who)
            self.stats["legacy_rmw_zenoh_sessions"] = len(self.legacy_sessions)
            log.warning("outputs.ros2: a ROS 2 node in domain %d (publishing %s) runs rmw_zenoh 0.2.0-0.2.3, which reads "
                        "another attachment layout and throws on vtolpose's messages: it needs rmw_zenoh >= 0.2.4 "
                        "(Jazzy) or >= 0.6.0 (Rolling)", self.names.domain_id, sample.key_expr)

    def publish(self, pose: OutputPose) -> None:
        if self._odom is None or self._tf is None or not pose.position_initialized:
            return
        if self._stamp_offset_ns is None:
            self._stamp_offset_ns = time.time_ns() - pose.t_ns
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
        for watcher in self._watchers:
            try:
                watcher.undeclare()
            except zenoh.ZError as exc:
                log.debug("ROS 2 watcher undeclare on close: %s", exc)
        self._watchers = []
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
