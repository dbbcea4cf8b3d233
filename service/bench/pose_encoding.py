"""What writing one ``<prefix>/pose`` message costs the event loop: the reference
``json.dumps(pose_message(...))`` against :class:`~vtolpose.service.outputs.pose_json.PoseJson`, and
PoseJson with the covariance's text written ahead (``PoseJson.prepare``, as the runtime does after a
pose left), in a warm loop over the poses of a short replayed flight (predicted and fused, as published).

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


Encoder = Callable[[OutputPose, int, Any], str]
Prepare = Callable[[OutputPose], None] | None


def _warm_us(encoders: list[Encoder], poses: list[OutputPose], prepares: list[Prepare] | None = None) -> list[float]:
    """Best of five passes over ``poses``, µs per message, the encoders taking turns pass by pass. ``prepares``:
    per encoder, what runs before each pose outside the timing (the covariance written ahead), or None."""
    prepares = prepares or [None] * len(encoders)
    best = [float("inf")] * len(encoders)
    for _ in range(5):
        for k, (encode, prepare) in enumerate(zip(encoders, prepares)):
            took = 0
            for seq, pose in enumerate(poses):
                if prepare is not None:
                    prepare(pose)
                t0 = time.perf_counter_ns()
                encode(pose, seq, ORIGIN)
                took += time.perf_counter_ns() - t0
            best[k] = min(best[k], took * 1e-9)
    return [b / len(poses) * 1e6 for b in best]


def _paced_us(encoders: list[Encoder], poses: list[OutputPose], period_s: float = 0.008,
              prepares: list[Prepare] | None = None) -> list[float]:
    """Median µs of each encoder when called once per ``period_s`` (as the live loop calls it, caches gone
    cold between samples), the encoders taking turns on each pose; ``prepares`` as in :func:`_warm_us`."""
    prepares = prepares or [None] * len(encoders)
    took: list[list[int]] = [[] for _ in encoders]
    for seq, pose in enumerate(poses):
        for encode, prepare, times in zip(encoders, prepares, took):
            if prepare is not None:
                prepare(pose)
            time.sleep(period_s)
            t0 = time.perf_counter_ns()
            encode(pose, seq, ORIGIN)
            times.append(time.perf_counter_ns() - t0)
    return [statistics.median(times) * 1e-3 for times in took]


def bench_pose_encoding() -> list[Row]:
    """json.dumps(pose_message) against PoseJson, and PoseJson with the covariance written ahead: warm, and paced at 125 Hz."""
    poses = published_poses()
    fast, ahead = PoseJson(), PoseJson()
    same = sum(fast(p, k, ORIGIN) == json.dumps(pose_message(p, k, ORIGIN)) for k, p in enumerate(poses))
    same_ahead = 0
    for k, p in enumerate(poses):
        ahead.prepare(p.pose_cov)
        same_ahead += ahead(p, k, ORIGIN) == json.dumps(pose_message(p, k, ORIGIN))
    reference = lambda p, k, o: json.dumps(pose_message(p, k, o))  # noqa: E731
    prepares: list[Prepare] = [None, None, lambda p: ahead.prepare(p.pose_cov)]  # as the runtime, after the last pose left
    old, new, new_ahead = _warm_us([reference, fast, ahead], poses, prepares)
    old_paced, new_paced, ahead_paced = _paced_us([reference, fast, ahead], poses[::len(poses) // 300 or 1],
                                                  prepares=prepares)
    return [
        ("pose message, json.dumps(pose_message), warm", old, "us", f"{len(poses)} poses of a landfill replay"),
        ("pose message, PoseJson, warm", new, "us", f"{same} of {len(poses)} byte-identical to the reference"),
        ("pose message, PoseJson, covariance written ahead, warm", new_ahead, "us",
         f"{same_ahead} of {len(poses)} byte-identical; the covariance's text made before the pose (PoseJson.prepare)"),
        ("pose message, reference / PoseJson, warm", old / new, "x", "the same poses, the same run"),
        ("pose message, PoseJson / PoseJson written ahead, warm", new / new_ahead, "x", "the same poses, the same run"),
        ("pose message, json.dumps(pose_message), paced", old_paced, "us", "median, one call per 8 ms as live"),
        ("pose message, PoseJson, paced", new_paced, "us", "median, one call per 8 ms as live"),
        ("pose message, PoseJson, covariance written ahead, paced", ahead_paced, "us", "median, one call per 8 ms as live"),
        ("pose message, reference / PoseJson, paced", old_paced / new_paced, "x", "the same poses, taking turns"),
        ("pose message, PoseJson / PoseJson written ahead, paced", new_paced / ahead_paced, "x", "the same poses, taking turns"),
    ]
