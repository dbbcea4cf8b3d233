"""The ROS 2 setup of docs/interop.md against a ROS 2 system as rmw_zenoh configures it by default.

A router and a ROS-side peer are Zenoh sessions opened from copies of rmw_zenoh's own default
configurations (tests/data/rmw_zenoh/: the router's ``peers_failover_brokering: false``, the node's
gossip to the router), on loopback; only the router's port changes (7447 -> a free one, so that
parallel runs cannot collide). vtolpose runs with the command line the docs give; the ROS side must
see its liveliness tokens (``ros2 node list``) and its Odometry (``ros2 topic echo /odom``), stamped
within a second of the system clock. Twice: the ROS side on the project's Zenoh, and on the Zenoh version
rmw_zenoh pins (Jazzy's rmw_zenoh 0.2.5 and later: Zenoh 1.4.0), run from a second environment (``.ci/run``
makes it as ``.venv-rmw-zenoh``; ``VTOLPOSE_RMW_ZENOH_PYTHON`` names another) by tests/rmw_zenoh_side.py.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import threading
import time
from pathlib import Path

import pytest
import zenoh

from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.service.cli import main

from test_ros2 import free_port
from test_ros2_wire import ODOMETRY_HASH, TF_HASH, CdrReader

REPO_ROOT = Path(__file__).resolve().parents[1]
CONFIGS = Path(__file__).parent / "data" / "rmw_zenoh"
PINNED_ZENOH = "1.4.0"  # what rmw_zenoh's Jazzy releases (zenoh_cpp_vendor 0.2.5 on) build against
PINNED_PYTHON = Path(os.environ.get("VTOLPOSE_RMW_ZENOH_PYTHON", REPO_ROOT / ".venv-rmw-zenoh" / "bin" / "python"))
ODOM_KEY = f"0/odom/nav_msgs::msg::dds_::Odometry_/{ODOMETRY_HASH}"


def docs_command() -> list[str]:
    """The command line in docs/interop.md's marked block, as words."""
    text = (REPO_ROOT / "docs" / "interop.md").read_text(encoding="utf-8")
    block = re.search(r"<!-- ros2-router-example.*?```sh\n(.*?)```", text, re.S)
    assert block, "docs/interop.md lost its ros2-router-example block"
    return shlex.split(block.group(1).replace("\\\n", " "))


def rmw_zenoh_session(name: str, port: int) -> zenoh.Session:
    conf = zenoh.Config.from_file(str(CONFIGS / f"DEFAULT_RMW_ZENOH_{name}_CONFIG.json5"))
    if name == "ROUTER":
        conf.insert_json5("listen/endpoints", json.dumps([f"tcp/[::]:{port}"]))
    else:
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/localhost:{port}"]))
    return zenoh.open(conf)


class RosSide:
    """What a ROS 2 node on rmw_zenoh learns: the graph's tokens and the Odometry with its arrival time."""

    def __init__(self, port: int) -> None:
        self.session = rmw_zenoh_session("SESSION", port)
        self.lock = threading.Lock()
        self.tokens: set[str] = set()
        self.odometry: list[tuple[int, int]] = []  # (stamp ns, system time on arrival ns)
        self.session.liveliness().declare_subscriber("@ros2_lv/0/**", self._token)
        self.session.declare_subscriber(ODOM_KEY, self._odom)

    def _token(self, sample) -> None:
        with self.lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.tokens.add(str(sample.key_expr))

    def _odom(self, sample) -> None:
        arrived = time.time_ns()
        sec, nanosec = CdrReader(bytes(sample.payload.to_bytes())).get("iI")
        with self.lock:
            self.odometry.append((sec * 1_000_000_000 + nanosec, arrived))


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("ros2_router") / "landfill"
    write_flight(simulate_flight("landfill", 30.0, 2), root)
    return root


def test_the_documented_setup_reaches_a_default_ros2_system(flight, capsys):
    port = free_port()
    router = rmw_zenoh_session("ROUTER", port)
    ros = RosSide(port)
    try:
        words = docs_command()
        assert words[:2] == ["vtolpose", "run"] and "--ros2" in words
        args = [w.replace("7447", str(port)).replace("DATASET", str(flight)) for w in words[1:]]
        code = main(args + ["--duration", "6", "--set", "outputs.ros2.stamp=system"])
        time.sleep(0.5)
    finally:
        ros.session.close()
        router.close()
    assert code == 0, capsys.readouterr().err
    node = [t for t in ros.tokens if t.split("/")[5] == "NN"]
    publishers = [t for t in ros.tokens if t.split("/")[5] == "MP"]
    assert len(node) == 1 and node[0].endswith("/NN/%/%/vtolpose"), ros.tokens
    assert any(f"/%odom/nav_msgs::msg::dds_::Odometry_/{ODOMETRY_HASH}/::,10:" in t for t in publishers), publishers
    assert any(f"/%tf/tf2_msgs::msg::dds_::TFMessage_/{TF_HASH}/::,100:" in t for t in publishers), publishers
    assert len(ros.odometry) > 200, len(ros.odometry)  # about 4 s of 200 Hz poses after the start
    late = [(arrived - stamp) * 1e-9 for stamp, arrived in ros.odometry]
    print(f"{len(ros.odometry)} Odometry through the router; stamp to arrival {min(late):.4f}..{max(late):.4f} s")
    assert max(abs(d) for d in late) < 1.0


def _check_ros_side(tokens: set[str], odometry: list[tuple[int, int]]) -> list[float]:
    """What a ROS 2 user must see: the node and its two publishers in the graph, Odometry stamped on the
    system clock. Returns the stamp-to-arrival delays."""
    node = [t for t in tokens if t.split("/")[5] == "NN"]
    publishers = [t for t in tokens if t.split("/")[5] == "MP"]
    assert len(node) == 1 and node[0].endswith("/NN/%/%/vtolpose"), tokens
    assert any(f"/%odom/nav_msgs::msg::dds_::Odometry_/{ODOMETRY_HASH}/::,10:" in t for t in publishers), publishers
    assert any(f"/%tf/tf2_msgs::msg::dds_::TFMessage_/{TF_HASH}/::,100:" in t for t in publishers), publishers
    assert len(odometry) > 200, len(odometry)  # about 4 s of 200 Hz poses after the start
    late = [(arrived - stamp) * 1e-9 for stamp, arrived in odometry]
    assert max(abs(d) for d in late) < 1.0
    return late


def test_the_documented_setup_reaches_a_ros2_system_on_the_zenoh_rmw_zenoh_pins(flight, capsys):
    if not PINNED_PYTHON.is_file():
        pytest.skip(f"needs a Python with eclipse-zenoh=={PINNED_ZENOH} at {PINNED_PYTHON} (.ci/run makes it; "
                    "VTOLPOSE_RMW_ZENOH_PYTHON names another)")
    port = free_port()
    side = subprocess.Popen([str(PINNED_PYTHON), str(Path(__file__).parent / "rmw_zenoh_side.py"), str(CONFIGS),
                             str(port), ODOM_KEY], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert side.stdout.readline().strip() == "ready", "the pinned-Zenoh ROS side did not start"
        args = [w.replace("7447", str(port)).replace("DATASET", str(flight)) for w in docs_command()[1:]]
        code = main(args + ["--duration", "6", "--set", "outputs.ros2.stamp=system"])
        time.sleep(0.5)
        out, _ = side.communicate("stop\n", timeout=30)
    finally:
        if side.poll() is None:
            side.kill()
    assert code == 0, capsys.readouterr().err
    seen = json.loads(out.strip().splitlines()[-1])
    assert seen["zenoh"] == PINNED_ZENOH, f"the ROS side ran Zenoh {seen['zenoh']}, not {PINNED_ZENOH}"
    late = _check_ros_side(set(seen["tokens"]), [tuple(x) for x in seen["odometry"]])
    print(f"Zenoh {seen['zenoh']} ROS side: {len(seen['odometry'])} Odometry; stamp to arrival "
          f"{min(late):.4f}..{max(late):.4f} s")
