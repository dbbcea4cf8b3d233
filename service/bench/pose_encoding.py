"""What writing one ``<prefix>/pose`` message costs the event loop: the reference
``json.dumps(pose_message(...))`` against :class:`~vtolpose.service.outputs.pose_json.PoseJson`,
in a warm loop over the poses of a short replayed flight (predicted and fused, as published).

Run: ``vtolpose bench --only pose-encoding``. The live loop, which sleeps between samples, pays
several times these warm figures; the ratio is what carries over.
"""

from __future__ import annotations

import json
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.estimator import OutputPose
from vtolpose.service.bench.rows import Row
from vtolpose.service.outputs.pose_json import PoseJson, pose_message
from vtolpose.service.replay.session import replay

ORIGIN = (59.91, 10.75, 120.0)


class _Collect:
    """An output that keeps every pose the runtime publishes."""

    name = "collect"

    def __init__(self) -> None:
        self.poses: list[OutputPose] = []

    def open(self) -> None: ...
    def publish(self, pose: OutputPose) -> None: self.poses.append(pose)
    def publish_status(self, status: dict[str, Any]) -> None: ...
    async def serve(self, stop: Any) -> None: await stop.wait()
    def close(self) -> None: ...


def published_poses(seconds: float = 20.0) -> list[OutputPose]:
    """The poses a landfill IMU+GPS replay of ``seconds`` publishes."""
    collect = _Collect()
    with tempfile.TemporaryDirectory() as tmp:
        write_flight(simulate_flight("landfill", seconds, 1), Path(tmp) / "d")
        replay(Dataset.open(Path(tmp) / "d"), load_config(None, {}), ["imu", "gps"],
               prepare=lambda runtime: runtime.outputs.append(collect))
    return collect.poses


def _warm_us(encoders: list[Callable[[OutputPose, int, Any], str]], poses: list[OutputPose]) -> list[float]:
    """Best of five passes over ``poses``, µs per message, the encoders taking turns pass by pass."""
    best = [float("inf")] * len(encoders)
    for _ in range(5):
        for k, encode in enumerate(encoders):
            t0 = time.perf_counter()
            for seq, pose in enumerate(poses):
                encode(pose, seq, ORIGIN)
            best[k] = min(best[k], time.perf_counter() - t0)
    return [b / len(poses) * 1e6 for b in best]


def _paced_us(encoders: list[Callable[[OutputPose, int, Any], str]], poses: list[OutputPose],
              period_s: float = 0.008) -> list[float]:
    """Median µs of each encoder when called once per ``period_s`` (as the live loop calls it, caches gone
    cold between samples), the encoders taking turns on each pose."""
    took: list[list[int]] = [[] for _ in encoders]
    for seq, pose in enumerate(poses):
        for encode, times in zip(encoders, took):
            time.sleep(period_s)
            t0 = time.perf_counter_ns()
            encode(pose, seq, ORIGIN)
            times.append(time.perf_counter_ns() - t0)
    return [statistics.median(times) * 1e-3 for times in took]


def bench_pose_encoding() -> list[Row]:
    """json.dumps(pose_message) against PoseJson: warm loop, and paced at 125 Hz as the live loop."""
    poses = published_poses()
    fast = PoseJson()
    same = sum(fast(p, k, ORIGIN) == json.dumps(pose_message(p, k, ORIGIN)) for k, p in enumerate(poses))
    reference = lambda p, k, o: json.dumps(pose_message(p, k, o))  # noqa: E731
    old, new = _warm_us([reference, fast], poses)
    old_paced, new_paced = _paced_us([reference, fast], poses[::len(poses) // 300 or 1])
    return [
        ("pose message, json.dumps(pose_message), warm", old, "us", f"{len(poses)} poses of a landfill replay"),
        ("pose message, PoseJson, warm", new, "us", f"{same} of {len(poses)} byte-identical to the reference"),
        ("pose message, reference / PoseJson, warm", old / new, "x", "the same poses, the same run"),
        ("pose message, json.dumps(pose_message), paced", old_paced, "us", "median, one call per 8 ms as live"),
        ("pose message, PoseJson, paced", new_paced, "us", "median, one call per 8 ms as live"),
        ("pose message, reference / PoseJson, paced", old_paced / new_paced, "x", "the same poses, taking turns"),
    ]
