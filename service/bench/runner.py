"""Benchmarks that answer "can my helicopter computer keep up?" — figures, not asserts.

Each benchmark returns :class:`~vtolpose.service.bench.rows.Row` figures, with a target and a
pass/short verdict where the figure has a target. Ratios are measured against a baseline taken in the
same run where a baseline makes sense.
"""

from __future__ import annotations

import tempfile
import time
import timeit
from pathlib import Path
from typing import Callable

import numpy as np

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.estimator import (
    FilterState, GpsFix, GpsUpdater, ImuDelta, ImuNoise, ImuPropagator, quat_from_euler, StateLayout,
)
from vtolpose.service.bench.catalog import GROUPS, LONG_BENCHMARKS
from vtolpose.service.bench.cold_start import bench_cold_start
from vtolpose.service.bench.rows import Row
from vtolpose.service.bench.faults import bench_fault_table, bench_fault_targets
from vtolpose.service.bench.sensor_lies import bench_sensor_lies
from vtolpose.service.bench.latency_floor import bench_latency_floor
from vtolpose.service.bench.runtime import bench_runtime_hour, bench_runtime_latency, bench_soak_camera
from vtolpose.service.bench.batch import bench_batch
from vtolpose.service.bench.camera_clock import bench_camera_clock
from vtolpose.service.bench.camera_mounting import bench_camera_mounting
from vtolpose.service.bench.camera_matrix import bench_camera_matrix
from vtolpose.service.bench.camera import bench_camera, bench_camera_update, bench_features, bench_replay_camera
from vtolpose.service.bench.camera_resolutions import bench_camera_resolutions
from vtolpose.service.bench.euroc import bench_euroc
from vtolpose.service.bench.euroc_causes import bench_euroc_causes
from vtolpose.service.bench.euroc_reference import bench_euroc_reference
from vtolpose.service.bench.memory_paced import bench_memory_paced
from vtolpose.service.bench.odometry_encoding import bench_odometry_encoding
from vtolpose.service.bench.pose_encoding import bench_pose_encoding
from vtolpose.service.bench.results import bench_results
from vtolpose.service.bench.zenoh_queries import bench_zenoh_queries
from vtolpose.service.bench.smoothing import (bench_smoothing_hour, bench_smoothing_landmarks, bench_smoothing_latency,
                                              bench_smoothing_sim)
from vtolpose.service.replay.session import replay
from vtolpose.service.runtime.kernels import load_compiled_kernels



def _per_call_us(fn: Callable[[], object], number: int) -> float:
    fn()
    best = min(timeit.repeat(fn, number=number, repeat=5))
    return best / number * 1e6


def bench_filter_steps() -> list[Row]:
    """Cost of one IMU propagation and one GPS update, both state variants."""
    rows: list[Row] = []
    noise = ImuNoise.isotropic(3e-4, 2e-5, 2e-3, 3e-4)
    gyro, accel = np.array([0.01, -0.02, 0.03]), np.array([0.2, -0.1, -9.8])
    for variant in ("thesis", "biases"):
        layout = StateLayout(variant)
        state = FilterState(layout)
        state.q = quat_from_euler(0.1, 0.05, 0.3)
        state.cov = np.eye(layout.robot_dim) * 1e-2
        prop = ImuPropagator(noise, 9.81)
        delta = ImuDelta(0, 10_000_000, 0.01, gyro * 0.01, accel * 0.01)
        rows.append((f"filter step, IMU delta ({variant})", _per_call_us(lambda: prop.propagate(state, delta), 5000), "us", "one step of <= 100 Hz"))
        upd = GpsUpdater(np.array([0.0, 0.0, -0.3]), gate=None)

        def gps_update() -> None:
            s = state.copy()
            upd.update(s, GpsFix(0, s.p + 0.01, 0.02, 0.03))

        rows.append((f"gps update ({variant})", _per_call_us(gps_update, 2000), "us", "includes a state copy"))
    return rows


REPLAY_TARGETS = {"book": ">= 300", "landfill": ">= 100"}  # x real time, IMU+GPS, both variants


REPLAY_ROUNDS = 3  # replays per variant; the median is the figure (one replay is a fraction of a second)


def bench_replay_speed(scenarios: tuple[tuple[str, float], ...] = (("book", 120.0), ("landfill", 300.0))) -> list[Row]:
    """IMU+GPS replay speed as a multiple of real time (targets: book ≥ 300×, landfill ≥ 100×): the median of
    three replays per variant, after one unmeasured replay, the files read beforehand (a row of their own)."""
    load_compiled_kernels()  # once per process, before the first replay (not in its time)
    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as tmp:
        for scenario, duration in scenarios:
            path = Path(tmp) / scenario
            write_flight(simulate_flight(scenario, duration, 1), path)
            dataset = Dataset.open(path)
            started = time.perf_counter()
            dataset.imu(), dataset.gps()
            rows.append((f"reading {scenario} {duration:g} s (IMU and GPS files)", (time.perf_counter() - started) * 1e3,
                         "ms", "once per replay command; not in the figures below"))
            replay(dataset, load_config(None, {}), ["imu", "gps"])  # first-use costs of the process
            for variant in ("thesis", "biases"):
                cfg = load_config(None, {"estimator": {"variant": variant}})
                results = [replay(dataset, cfg, ["imu", "gps"]) for _ in range(REPLAY_ROUNDS)]
                walls = sorted(r.wall_s for r in results)
                rate = results[0].duration_s / walls[len(walls) // 2]
                rows.append(Row(f"replay imu,gps {scenario} {duration:g} s ({variant})", rate, "x real time",
                                f"median of {REPLAY_ROUNDS}: {', '.join(f'{w:.2f}' for w in walls)} s wall",
                                REPLAY_TARGETS.get(scenario)))
    return rows


BENCHMARKS: dict[str, Callable[[], list[Row]]] = {
    "filter-steps": bench_filter_steps,
    "replay-speed": bench_replay_speed,
    "camera-update": bench_camera_update,
    "features": bench_features,
    "replay-camera": bench_replay_camera,
    "camera-resolutions": bench_camera_resolutions,
    "camera": bench_camera,
    "odometry-encoding": bench_odometry_encoding,
    "runtime-latency": bench_runtime_latency,
    "latency-floor": bench_latency_floor,
    "pose-encoding": bench_pose_encoding,
    "runtime-hour": bench_runtime_hour,
    "soak-camera": bench_soak_camera,
    "fault-targets": bench_fault_targets,
    "fault-table": bench_fault_table,
    "sensor-lies": bench_sensor_lies,
    "euroc": bench_euroc,
    "euroc-reference": bench_euroc_reference,
    "euroc-causes": bench_euroc_causes,
    "zenoh-queries": bench_zenoh_queries,
    "memory-paced": bench_memory_paced,
    "smoothing-sim": bench_smoothing_sim,
    "smoothing-landmarks": bench_smoothing_landmarks,
    "smoothing-hour": bench_smoothing_hour,
    "smoothing-latency": bench_smoothing_latency,
    "batch": bench_batch,
    "results": bench_results,
    "cold-start": bench_cold_start,
    "camera-matrix": bench_camera_matrix,
    "camera-clock": bench_camera_clock,
    "camera-mounting": bench_camera_mounting,
}


def run_benchmarks(names: list[str] | None = None, echo: Callable[[str], None] = print, include_long: bool = False) -> list[Row]:
    """Run ``names`` (default: all but the long ones), print each figure as it comes, then a verdict line."""
    rows: list[Row] = []
    default = [n for n in BENCHMARKS if (include_long or n not in LONG_BENCHMARKS) and n not in GROUPS]
    for name in names or default:
        if name not in BENCHMARKS:
            raise ValueError(f"unknown benchmark {name!r}; choose from {', '.join(BENCHMARKS)}")
        t0 = time.perf_counter()
        got = BENCHMARKS[name]()
        for row in got:
            echo(Row(*row).line())
        echo(f"  ({name}: {time.perf_counter() - t0:.1f} s)")
        rows.extend(Row(*row) for row in got)
    judged = [r for r in rows if r.target is not None]
    short = [r for r in judged if r.verdict == "short"]
    echo(f"verdict: {len(judged) - len(short)} of {len(judged)} figures with a target pass"
         + (f"; short: {', '.join(r.name for r in short)}" if short else ""))
    return rows
