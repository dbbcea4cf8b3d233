"""A ROS 2 system as rmw_zenoh configures it by default, on whatever Zenoh the running Python has: a router
and a ROS-side session opened from the copies of rmw_zenoh's default configurations in tests/data/rmw_zenoh/.

Run by tests/test_ros2_router.py with the Python of a second environment that holds the Zenoh version
rmw_zenoh pins, so that vtolpose (on the project's Zenoh) is tested against that version over the wire.
Standalone: only Zenoh and the standard library. Prints ``ready`` once both sessions are open, collects the
graph's liveliness tokens and the Odometry stamps until a line arrives on stdin, then prints them as JSON.

    python rmw_zenoh_side.py CONFIG_DIR PORT ODOM_KEY
"""

from __future__ import annotations

import json
import struct
import sys
import threading
import time
from importlib import metadata

import zenoh


def main(config_dir: str, port: int, odom_key: str) -> None:
    router_conf = zenoh.Config.from_file(f"{config_dir}/DEFAULT_RMW_ZENOH_ROUTER_CONFIG.json5")
    router_conf.insert_json5("listen/endpoints", json.dumps([f"tcp/[::]:{port}"]))
    node_conf = zenoh.Config.from_file(f"{config_dir}/DEFAULT_RMW_ZENOH_SESSION_CONFIG.json5")
    node_conf.insert_json5("connect/endpoints", json.dumps([f"tcp/localhost:{port}"]))
    lock, tokens, odometry = threading.Lock(), set(), []

    def on_token(sample) -> None:
        with lock:
            if sample.kind == zenoh.SampleKind.PUT:
                tokens.add(str(sample.key_expr))

    def on_odom(sample) -> None:
        arrived = time.time_ns()
        payload = bytes(sample.payload.to_bytes())
        sec, nanosec = struct.unpack_from("<iI", payload, 4)  # after the 4-byte CDR encapsulation header
        with lock:
            odometry.append((sec * 1_000_000_000 + nanosec, arrived))

    router = zenoh.open(router_conf)
    node = zenoh.open(node_conf)
    node.liveliness().declare_subscriber("@ros2_lv/0/**", on_token)
    node.declare_subscriber(odom_key, on_odom)
    print("ready", flush=True)
    sys.stdin.readline()
    with lock:
        out = {"zenoh": metadata.version("eclipse-zenoh"), "tokens": sorted(tokens), "odometry": odometry}
    node.close()
    router.close()
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), sys.argv[3])
