"""Camera benchmarks: feature extraction, one EKF-SLAM update vs map size, Test 3 replay speed.

Rows are (name, value, unit, note), as in ``vtolpose.service.bench.runner``. The EKF-SLAM update grows with the
map: the innovation covariance and gain touch every state (O(n m) for m measurement rows), the
covariance update is O(n² m); these figures show where a map cap has to sit on this computer.
"""

from __future__ import annotations

import itertools
import tempfile
import time
import timeit
from pathlib import Path

import cv2
import numpy as np

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.drivers.simulator.render import default_camera, render_frames
from vtolpose.estimator.vision.camera_pipeline import CameraOptions, CameraPipeline
from vtolpose.estimator.vision.camera_update import predict
from vtolpose.estimator.vision.features import DETECTORS, FeatureOptions, FrameFeatures, extract_features
from vtolpose.estimator.vision.map_manager import MapOptions
from vtolpose.estimator.core.rotation import quat_from_euler
from vtolpose.estimator.core.state import FilterState, StateLayout
from vtolpose.service.replay.session import replay
from vtolpose.service.runtime.threads import limit_blas_threads
from vtolpose.service.bench.rows import Row

MAP_SIZES = (10, 30, 60, 100)


def _grid(n: int, width: int, height: int) -> np.ndarray:
    cols = int(np.ceil(np.sqrt(n * width / height)))
    rows = int(np.ceil(n / cols))
    gx, gy = np.meshgrid(np.linspace(30, width - 30, cols), np.linspace(30, height - 30, rows))
    return np.column_stack([gx.ravel(), gy.ravel()])[:n]


def _scene(variant: str, n: int, depth_known: bool) -> tuple[FilterState, CameraPipeline, FrameFeatures]:
    """``n`` landmarks in view from 30 m and a frame that matches all of them.

    With ``depth_known`` the landmarks count as observed (one stacked EKF update, the steady
    state); otherwise as guessed (the iterated update a landmark gets in its first frames).
    """
    cam = default_camera()
    state = FilterState(StateLayout(variant))
    state.p = np.array([0.0, 0.0, -30.0])
    state.q = quat_from_euler(0.02, -0.01, 0.3)
    state.cov = np.eye(state.robot_dim) * 1e-4
    pipe = CameraPipeline(cam, CameraOptions(map=MapOptions(max_landmarks=n, target_in_view=n, max_new_per_frame=n,
                                                            min_feature_distance_px=5.0, depth_sigma_rel=0.05)))
    rng = np.random.default_rng(0)
    desc = rng.normal(size=(n, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    uv = _grid(n, cam.width, cam.height)
    pipe.process(state, FrameFeatures(0, uv, desc, np.arange(n, 0, -1.0), (cam.height, cam.width)), 0, True, True)
    if depth_known:
        pipe.book.sigma_rho0[:] = 1.0  # as if born with Civera's prior ...
        pipe.book.settled[:] = 100  # ... and observed since
    seen = predict(state, pipe.camera, pipe.R_BC, pipe.t_BC, 1.0).uv + rng.normal(0.0, 0.5, size=(n, 2))
    return state, pipe, FrameFeatures(1, seen, pipe.book.descriptors.copy(), np.arange(n, 0, -1.0), (cam.height, cam.width))


def bench_camera_update() -> list[Row]:
    """One camera update (predict, associate, stacked EKF update) vs landmarks in the map."""
    limit_blas_threads(1)
    rows: list[Row] = []
    for depth_known in (True, False):
        for variant in ("thesis", "biases"):
            for n in MAP_SIZES:
                state, pipe, frame = _scene(variant, n, depth_known)
                copy_s = min(timeit.repeat(state.copy, number=10, repeat=5)) / 10
                run_s = min(timeit.repeat(lambda: pipe.process(state.copy(), frame, 1, False, True), number=10, repeat=5)) / 10
                check = pipe.process(state.copy(), frame, 1, False, True)
                label = f"{n} landmarks ({variant})" if depth_known else f"{n} guessed ({variant}, iterated)"
                rows.append((f"camera update, {label}", (run_s - copy_s) * 1e3, "ms",
                             f"{check.n_matches} matches, state dim {state.dim}"))
    return rows


def _frames(scenario: str, duration_s: float, first: int, count: int) -> list[np.ndarray]:
    flight = simulate_flight(scenario, duration_s, 1)
    return [image for _, image in itertools.islice(render_frames(flight), first, first + count)]


def bench_features() -> list[Row]:
    """Feature extraction per 656 x 494 frame, each detector, on rendered book and landfill frames."""
    rows: list[Row] = []
    sets = {"book": _frames("book", 16.0, 100, 12), "landfill": _frames("landfill", 62.0, 440, 12)}
    for detector in DETECTORS:
        try:
            options = FeatureOptions(detector=detector)
        except ValueError as exc:
            rows.append((f"features {detector}", float("nan"), "ms", str(exc)))
            continue
        for name, images in sets.items():
            extract_features(images[0], 0, options)
            started = time.perf_counter()
            counts = [len(extract_features(image, 0, options)) for image in images]
            per_frame = (time.perf_counter() - started) / len(images) * 1e3
            rows.append(Row(f"features {detector}, {name}", per_frame, "ms/frame",
                            f"{np.mean(counts):.0f} features, OpenCV {cv2.getNumThreads()} threads", "<= 25"))
    return rows


TEST3_TARGETS = {"sift": ">= 5", "orb": ">= 20"}  # x real time (SIFT is the default detector)


def bench_replay_camera(scenario: str = "book", duration_s: float = 120.0) -> list[Row]:
    """Test 3 (imu,camera,gps) replay speed as a multiple of real time, SIFT and ORB, both variants."""
    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as tmp:
        started = time.perf_counter()
        path = write_flight(simulate_flight(scenario, duration_s, 1), Path(tmp) / scenario, camera=default_camera())
        rows.append((f"render {scenario} {duration_s:g} s ({int(duration_s * 7.5)} frames)", time.perf_counter() - started,
                     "s", "includes writing the PNGs"))
        dataset = Dataset.open(path)
        for detector in ("sift", "orb"):
            for variant in ("thesis", "biases"):
                cfg = load_config(None, {"estimator": {"variant": variant}, "features": {"detector": detector}})
                result = replay(dataset, cfg, ["imu", "camera", "gps"])
                rate = result.duration_s / result.wall_s
                extract = float(np.mean(result.extract_ms))
                filt = float(np.mean([f.timing_ms["total"] for f in result.frames if f.timing_ms]))
                rows.append(Row(f"replay imu,camera,gps {scenario} {detector} ({variant})", rate, "x real time",
                                f"{result.wall_s:.1f} s wall; per frame: extract {extract:.1f} ms, filter {filt:.1f} ms",
                                TEST3_TARGETS[detector]))
    return rows
