"""Foxglove live view and MCAP recording: a paced replay of a rendered flight serves the view to a real
WebSocket client (``websockets``) and records one MCAP file, read back with the ``mcap`` library;
the raw samples in it are decoded with ``rosbags`` and compared with the dataset."""

import json
import struct
import threading
import time

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.typesys import Stores, get_typestore
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.drivers.simulator.render import default_camera
from vtolpose.service.cli import build_parser
from vtolpose.service.commands.run import config_for
from vtolpose.service.replay.session import replay

from conftest import free_port

ROS = get_typestore(Stores.ROS2_JAZZY)
VIEW_TOPICS = {"/tf", "/pose", "/path", "/covariance", "/gps", "/gps/local", "/landmarks", "/camera/image",
               "/camera/overlay", "/status"}
RECORDED_TOPICS = VIEW_TOPICS | {"/vtolpose/pose", "/imu", "/gps/fix", "/camera/image_raw/compressed"}


class ViewClient:
    """A Foxglove WebSocket client: subscribes to every advertised channel and counts what arrives."""

    def __init__(self, port: int, timeout_s: float = 20.0) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self.ws = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=2, legacy=True)
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)
        self.server_info: dict = {}
        self.topics: dict[int, str] = {}
        self.received: dict[str, list[bytes]] = {}

    def run_until(self, done) -> None:
        """Read until ``done()`` and a quiet half second, or until the server goes away."""
        quiet_since = None
        while True:
            try:
                frame = self.ws.recv(timeout=0.5)
            except TimeoutError:
                if done():
                    if quiet_since is not None and time.monotonic() - quiet_since > 0.5:
                        return
                    quiet_since = quiet_since or time.monotonic()
                continue
            except ConnectionClosed:
                return
            if isinstance(frame, str):
                self._control(json.loads(frame))
            else:
                op, sub_id, _log_time = struct.unpack_from("<BIQ", frame)
                assert op == 1  # message data
                self.received.setdefault(self.topics[sub_id], []).append(frame[13:])

    def _control(self, doc: dict) -> None:
        if doc["op"] == "serverInfo":
            self.server_info = doc
        elif doc["op"] == "advertise":
            subs = [{"id": c["id"], "channelId": c["id"]} for c in doc["channels"]]
            self.topics.update({c["id"]: c["topic"] for c in doc["channels"]})
            self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    root = tmp_path_factory.mktemp("fox")
    flight = write_flight(simulate_flight("landfill", 10.0, 2), root / "landfill", camera=default_camera())
    port, mcap_path = free_port(), root / "flight.mcap"
    cfg = load_config(None, {"outputs": {"foxglove": {"enabled": True, "port": port}, "mcap": {"file": str(mcap_path)}}})
    out: dict = {}

    def run() -> None:
        try:
            # Lock-step (speed 0): every frame is processed however busy the machine is; the client is
            # subscribed long before the replay of 75 frames ends.
            out["result"] = replay(Dataset.open(flight), cfg, ["imu", "camera", "gps"], speed=0.0)
        except BaseException as exc:  # surfaced in the test
            out["error"] = exc

    worker = threading.Thread(target=run)
    worker.start()
    client = ViewClient(port)
    client.run_until(lambda: not worker.is_alive())
    worker.join(60)
    if "error" in out:
        raise out["error"]
    return flight, mcap_path, client, out["result"]


def test_view_client_gets_every_channel(recorded):
    _, _, client, result = recorded
    assert client.server_info["name"] == "vtolpose"
    assert set(client.topics.values()) == VIEW_TOPICS
    assert VIEW_TOPICS <= set(client.received), f"no message on {VIEW_TOPICS - set(client.received)}"
    status = json.loads(client.received["/status"][-1])
    assert status["sensors"]["camera"]["total"] > 0 and "quality" in status
    assert all(b"\xff\xd8\xff" in m for m in client.received["/camera/image"])  # JPEG inside each picture
    assert max(map(len, client.received["/camera/overlay"])) > 1000  # features, gates, matches drawn
    assert len(client.received["/pose"]) > 50
    assert not result.failures, result.failures  # no output, tap or viewer failed on the way
    for name in ("foxglove", "mcap"):
        assert status["outputs"][name]["failures"] == 0 and status["outputs"][name]["dropped_full"] == 0


def test_mcap_has_every_channel_and_the_raw_samples(recorded):
    flight, mcap_path, _, result = recorded
    dataset = Dataset.open(flight)
    with mcap_path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        counts = summary.statistics.channel_message_counts
        by_topic = {c.topic: c for c in summary.channels.values()}
        assert set(by_topic) == RECORDED_TOPICS
        assert all(counts[c.id] > 0 for c in by_topic.values())
        assert summary.schemas[by_topic["/imu"].schema_id].encoding == "ros2msg"
        imu, gps = dataset.imu(), dataset.gps()
        assert counts[by_topic["/imu"].id] == len(imu.t_ns)
        assert counts[by_topic["/gps/fix"].id] == len(gps.t_ns)
        assert counts[by_topic["/camera/image_raw/compressed"].id] == len(dataset.camera_frames())
        first = {}
        for _schema, channel, message in reader.iter_messages(topics=["/imu", "/gps/fix", "/camera/image_raw/compressed"]):
            first.setdefault(channel.topic, message)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        poses = [json.loads(m.data) for _s, _c, m in reader.iter_messages(topics=["/vtolpose/pose"])]

    msg = ROS.deserialize_cdr(first["/imu"].data, "sensor_msgs/msg/Imu")
    assert first["/imu"].log_time == imu.t_ns[0]
    w, a = msg.angular_velocity, msg.linear_acceleration
    assert np.allclose([w.x, -w.y, -w.z], imu.gyro[0]) and np.allclose([a.x, -a.y, -a.z], imu.accel[0])  # FLU
    fix = ROS.deserialize_cdr(first["/gps/fix"].data, "sensor_msgs/msg/NavSatFix")
    wgs84 = np.loadtxt(flight / "mav0/gps0/data.csv", delimiter=",", comments="#", ndmin=2)
    assert abs(fix.latitude - wgs84[0, 1]) < 1e-9 and abs(fix.longitude - wgs84[0, 2]) < 1e-9
    assert np.isclose(fix.position_covariance[0], wgs84[0, 4] ** 2)
    png = ROS.deserialize_cdr(first["/camera/image_raw/compressed"].data, "sensor_msgs/msg/CompressedImage")
    t0, path0 = dataset.camera_frames()[0]
    assert png.format == "png" and np.array_equal(cv2.imdecode(png.data, cv2.IMREAD_UNCHANGED), dataset.load_frame(path0))
    assert (png.header.stamp.sec * 10**9 + png.header.stamp.nanosec) == t0

    assert len(poses) > 500 and all(p["frame"] == "NED" for p in poses)
    assert [p["seq"] for p in poses] == list(range(1, len(poses) + 1))
    assert poses[-1]["quality"] > 0 and len(poses[-1]["cov"]) == 36
    origin = tuple(float(x) for x in meta["vtolpose"]["origin_lat_lon_alt"].split(","))
    assert np.allclose(origin, gps.origin_lla)
    assert result.trajectory.t_ns[-1] <= poses[-1]["t_ns"]  # the estimates run ahead of the fused trajectory


def test_flags_fold_into_the_configuration(tmp_path):
    args = build_parser().parse_args(["replay", "data", "--foxglove", "--mcap", str(tmp_path / "x.mcap"), "--ros2"])
    cfg = config_for(args)
    assert cfg["outputs.foxglove.enabled"] and cfg["outputs.foxglove.port"] == 8765 and cfg["outputs.ros2.enabled"]
    assert cfg["outputs.mcap.file"] == str(tmp_path / "x.mcap")
    assert config_for(build_parser().parse_args(["run", "--foxglove", "9000"]))["outputs.foxglove.port"] == 9000
    assert not config_for(build_parser().parse_args(["run"]))["outputs.foxglove.enabled"]


def test_an_existing_recording_is_never_overwritten(tmp_path):
    from vtolpose.service.outputs.mcap import McapOutput

    (tmp_path / "old.mcap").write_bytes(b"flight")
    with pytest.raises(FileExistsError, match="never overwritten"):
        McapOutput(tmp_path / "old.mcap", 20.0, 100)
    assert (tmp_path / "old.mcap").read_bytes() == b"flight"
