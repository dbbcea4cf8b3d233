"""``vtolpose bench --only camera-resolutions``: Test 3's speed at the frame sizes and rate a speed target names.

The camera bench's Test 3 runs the book's own camera (656 × 494 at 7.5 Hz). The targets are stated for a
10-Hz camera at 640 × 480 and at 1280 × 720, so here the same book flight (seed 1) is rendered through each of
those two cameras (``drivers.simulator.cameras.matrix_camera``, radial-tangential lens) and replayed with the
default configuration: SIFT on every frame, then SIFT with optical flow between detections
(``features.track_between``), each with its accuracy beside its speed (÷ SIFT on every frame, same frames).
The real-time factor is wall clock; the process's CPU time and the per-frame work (extraction in the
camera workers, the update on the fusion loop) say where the time goes.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.cameras import matrix_camera
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.config import load_config
from vtolpose.service.bench.rows import Row
from vtolpose.service.replay.report import build_report
from vtolpose.service.replay.session import replay
from vtolpose.service.runtime.kernels import load_compiled_kernels

RATE_HZ = 10.0
DURATION_S = 30.0
SIZES = {(640, 480): ">= 10", (1280, 720): ">= 3"}  # Test 3, x real time, SIFT
TRACK_BETWEEN = 4  # as the camera bench's tracked variant: SIFT on one frame in five
ACCURACY_TARGET = "<= 1.1"  # the tracked variant's RMSE ÷ SIFT on every frame's


def replay_test3(dataset: Dataset, features: dict) -> tuple[Any, float, tuple[float, float], np.ndarray]:
    """Test 3 (imu,camera,gps, biases) of ``dataset`` with these ``features.*``: the replay, its CPU seconds, its
    (position m, attitude deg) RMSE and each frame's update time on the fusion loop (CPU ms)."""
    cfg = load_config(None, {"estimator": {"variant": "biases"}, "features": features})
    cpu0 = time.process_time()
    result = replay(dataset, cfg, ["imu", "camera", "gps"])
    cpu_s = time.process_time() - cpu0
    report = build_report(result, dataset, cfg)
    update_ms = np.array([f.timing_ms["cpu"] for f in result.frames if f.timing_ms])
    return result, cpu_s, (report["position_rmse_m"], report.get("attitude_rmse_deg", float("nan"))), update_ms


def bench_camera_resolutions(duration_s: float = DURATION_S) -> list[Row]:
    """Test 3 (imu,camera,gps, biases) on the book flight seen at 10 Hz through a 640 × 480 and a 1280 × 720
    camera: speed with SIFT on every frame and with flow between detections, and the latter's accuracy."""
    load_compiled_kernels()  # once per process, before the first replay (not in its time)
    rows: list[Row] = []
    flight = simulate_flight("book", duration_s, 1)
    with tempfile.TemporaryDirectory() as tmp:
        for (width, height), target in SIZES.items():
            size = f"{width} x {height} at {RATE_HZ:g} Hz"
            started = time.perf_counter()
            root = write_flight(flight, Path(tmp) / f"book-{width}", camera=matrix_camera("radtan", width, height, RATE_HZ))
            rows.append(Row(f"render book {duration_s:g} s, {size}", time.perf_counter() - started, "s",
                            f"{int(duration_s * RATE_HZ)} frames, includes writing the PNGs"))
            dataset = Dataset.open(root)
            scores = {}
            for label, features, label_target in (("sift", {"detector": "sift"}, target),
                                                  ("sift + flow", {"detector": "sift", "track_between": TRACK_BETWEEN}, None)):
                result, cpu_s, scores[label], update_ms = replay_test3(dataset, features)
                rows.append(Row(f"Test 3 {size}, {label}", result.duration_s / result.wall_s, "x real time",
                                f"{result.wall_s:.1f} s wall, {result.duration_s / cpu_s:.1f} x on the process's CPU time; "
                                f"per frame p50: extraction {np.median(result.extract_cpu_ms):.1f} ms (one core), "
                                f"update {np.median(update_ms):.1f} ms (the fusion loop); RMSE {scores[label][0]:.4f} m, "
                                f"{scores[label][1]:.3f} deg", label_target))
            (p, a), (base_p, base_a) = scores["sift + flow"], scores["sift"]
            rows.append(Row(f"Test 3 {size}, sift + flow: position RMSE / sift's", p / base_p, "ratio",
                            f"{p:.4f} m vs {base_p:.4f} m", ACCURACY_TARGET))
            rows.append(Row(f"Test 3 {size}, sift + flow: attitude RMSE / sift's", a / base_a, "ratio",
                            f"{a:.3f} deg vs {base_a:.3f} deg", ACCURACY_TARGET))
    return rows
