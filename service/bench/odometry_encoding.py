"""``odometry-encoding``: what one ODOMETRY publish costs, framed by pymavlink and framed by hand.

Both paths run in the same process on the same poses, in a warm loop, through a real
:class:`~vtolpose.service.outputs.mavlink_output.Endpoint` sending over UDP on loopback (so the socket's
``sendto`` is in both). The pymavlink path is what ``MavlinkOutput.publish`` did per endpoint
before: ``MAVLink_odometry_message(**fields)`` through pymavlink's ``send``. Live, between IMU
samples, every figure is several times larger (cold caches); the ratio is what carries over.
"""

from __future__ import annotations

import math
import socket
import timeit
from typing import Any, Callable

import numpy as np

from vtolpose.config.mavlink_settings import EndpointSpec
from vtolpose.estimator import OutputPose, quat_from_euler
from vtolpose.service.bench.rows import Row
from vtolpose.service.outputs.mavlink_output import COMPONENT_ID, Endpoint, mav
from vtolpose.service.outputs.mavlink_odometry import (
    ODOMETRY_CRC_EXTRA, ODOMETRY_ID, PROFILES, odometry_fields, odometry_payload,
)

_POSE_ROWS = [0, 1, 2, 6, 7, 8]


def bench_poses(count: int = 16, seed: int = 4) -> list[OutputPose]:
    """Usable poses in flight: metres off the origin, a few m/s, attitude and covariance of a working filter."""
    rng = np.random.default_rng(seed)
    poses = []
    for i in range(count):
        a = rng.normal(size=(9, 9)) * 0.01
        cov9 = a @ a.T + np.diag([0.04] * 3 + [0.01] * 3 + [math.radians(0.5) ** 2] * 3)
        q = quat_from_euler(*rng.uniform(-0.2, 0.2, 2), rng.uniform(-math.pi, math.pi))
        t_ns = 10**12 + i * 8_000_000
        poses.append(OutputPose(t_ns, rng.normal(size=3) * 50.0, rng.normal(size=3) * 5.0, q, rng.normal(size=3) * 0.2,
                                cov9, cov9[np.ix_(_POSE_ROWS, _POSE_ROWS)], np.full(3, 1e-4), True, True, 2, t_ns))
    return poses


def _per_call_us(fn: Callable[[], Any], number: int) -> float:
    fn()
    return min(timeit.repeat(fn, number=number, repeat=5)) / number * 1e6


def bench_odometry_encoding(number: int = 2000) -> list[Row]:
    """µs per ODOMETRY publish to one endpoint, pymavlink's framing and the hand-built one, unsigned and signed."""
    poses = bench_poses()
    rows: list[Row] = []
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sink:  # never read: the kernel drops what overflows
        sink.bind(("127.0.0.1", 0))
        url = f"udpout:127.0.0.1:{sink.getsockname()[1]}"
        for signed in (False, True):
            spec = EndpointSpec("bench", url, "autopilot", 125.0, None, False, "bench")
            endpoint = Endpoint(spec, bytes(range(32)) if signed else None, PROFILES["px4"], 1, COMPONENT_ID)
            endpoint.open()
            profile, i = endpoint.profile, [0]

            def next_pose() -> OutputPose:
                i[0] = (i[0] + 1) % len(poses)
                return poses[i[0]]

            def with_pymavlink() -> None:
                f = odometry_fields(next_pose(), profile)
                endpoint.send(mav.MAVLink_odometry_message(**f), "odometry_sent")

            def by_hand() -> None:
                f = odometry_fields(next_pose(), profile)
                endpoint.send_packed(ODOMETRY_ID, ODOMETRY_CRC_EXTRA, odometry_payload(f), "odometry_sent")

            f0 = odometry_fields(poses[0], profile)
            fields_us = _per_call_us(lambda: odometry_fields(next_pose(), profile), number)
            encode_old = _per_call_us(lambda: endpoint.send(mav.MAVLink_odometry_message(**f0), "odometry_sent"), number)
            encode_new = _per_call_us(lambda: endpoint.send_packed(ODOMETRY_ID, ODOMETRY_CRC_EXTRA, odometry_payload(f0),
                                                                   "odometry_sent"), number)
            old, new = _per_call_us(with_pymavlink, number), _per_call_us(by_hand, number)
            endpoint.close()
            kind = "signed" if signed else "unsigned"
            rows += [
                Row(f"ODOMETRY publish, pymavlink framing ({kind})", old, "us", "fields + message + pack + sendto"),
                Row(f"ODOMETRY publish, framed by hand ({kind})", new, "us", f"{old / new:.2f}x faster"),
                Row(f"  fields from the pose ({kind})", fields_us, "us", "odometry_fields, in both"),
                Row(f"  encode + send, pymavlink ({kind})", encode_old, "us", "given the fields"),
                Row(f"  encode + send, by hand ({kind})", encode_new, "us", f"{encode_old / encode_new:.2f}x faster"),
            ]
    return rows
