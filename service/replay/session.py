"""Replay: a dataset fed through the onboard runtime, recorded for the report.

The same runtime as ``vtolpose run`` (fusion horizon, camera work off the loop, outputs when
enabled), fed by the dataset instead of devices. At ``speed`` 0 (the default) it runs as fast
as the machine allows in lock-step: camera work is awaited at the fusion horizon, so the result
does not depend on the machine. The recorder keeps every fused pose (the TUM trajectory) and,
at a lower rate, the pose covariance for the consistency (NEES) check.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.files.lidar import lidar_summary
from vtolpose.estimator import (
    CameraFrame, Estimator, FeatureOptions, FrameExtractor, FrameFeatures, FrameReport, FusedRun, OutputPose, make_room,
)
from vtolpose.service.replay.faults import Fault, FaultInjector
from vtolpose.service.runtime.kernels import KernelLoad, load_compiled_kernels
from vtolpose.service.runtime.replay_feed import checked_sensors, run_replay
from vtolpose.service.runtime.step_taps import SmoothingPlan
from vtolpose.service.runtime.threads import limit_blas_threads
from vtolpose.service.runtime.wiring import config_sections, feature_options

log = logging.getLogger(__name__)

# Called after each frame with the image, its features and what the filter did with them.
FrameCallback = Callable[[np.ndarray | None, FrameFeatures, FrameReport], None]


@dataclass
class Trajectory:
    t_ns: np.ndarray
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    unscored: np.ndarray | None = None  # (N,) bool: no position yet

    @property
    def valid(self) -> np.ndarray:
        return np.ones(len(self.t_ns), dtype=bool) if self.unscored is None else ~self.unscored


@dataclass
class CovarianceSamples:
    """Pose covariance ([δp, δθ], 6 × 6) sampled at a low rate, with the pose it belongs to."""

    t_ns: np.ndarray
    p: np.ndarray
    q: np.ndarray
    cov: np.ndarray

    @classmethod
    def from_rows(cls, rows: list[tuple]) -> CovarianceSamples:
        """From ``(t_ns, p, q, cov)`` rows as the recorders collect them."""
        if not rows:
            return cls(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 6, 6)))
        t, p, q, c = zip(*rows)
        return cls(np.array(t, dtype=np.int64), np.array(p), np.array(q), np.array(c))


class _Columns:
    """The trajectory's columns (t, p, v, q, unscored) in arrays that double when full: a run's poses are
    copied in as blocks, a single pose as a row, in the order they come (no rows or blocks to join later)."""

    def __init__(self, capacity: int = 4096) -> None:
        self.n = 0
        self._arrays = (np.empty(capacity, np.int64), np.empty((capacity, 3)), np.empty((capacity, 3)),
                        np.empty((capacity, 4)), np.empty(capacity, bool))

    def room_for(self, m: int) -> tuple[np.ndarray, ...]:
        """The arrays, with room for ``m`` more poses after the first :attr:`n`."""
        if self.n + m > len(self._arrays[0]):
            self._arrays, _, self.n = make_room(self._arrays, 0, self.n, m)
        return self._arrays

    def taken(self) -> tuple[np.ndarray, ...]:
        """Copies of the first :attr:`n` poses of each column."""
        return tuple(column[:self.n].copy() for column in self._arrays)


class Recorder:
    """Every fused pose, and its covariance at a lower rate (called on the runtime's loop)."""

    def __init__(self, cov_period_ns: int, absolute_position: bool = True) -> None:
        self._columns = _Columns()
        self.cov_period_ns = cov_period_ns
        # Without an absolute position source the start is the origin and the covariance is
        # meaningful from the first step; with one, only once the position is initialised.
        self.absolute_position = absolute_position
        self._next_cov_t = 0
        self._cov: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []

    def record(self, pose: OutputPose) -> None:
        # A pose before the position it is to have is not scored.
        unscored = self.absolute_position and not pose.position_initialized
        columns = self._columns
        t, p, v, q, flags = columns.room_for(1)
        k = columns.n
        t[k], p[k], v[k], q[k], flags[k] = pose.t_ns, pose.p, pose.v, pose.q, unscored
        columns.n = k + 1
        if not unscored and pose.t_ns >= self._next_cov_t:
            self._cov.append((pose.t_ns, pose.p, pose.q, pose.pose_cov))
            self._next_cov_t = pose.t_ns + self.cov_period_ns

    def record_run(self, run: FusedRun) -> None:
        """:meth:`record` for each pose of ``run``, without making them."""
        unscored = self.absolute_position and not run.position_initialized
        columns, t_ns = self._columns, run.t_ns
        m = len(t_ns)
        t, p, v, q, flags = columns.room_for(m)
        k = columns.n
        t[k:k + m], p[k:k + m], v[k:k + m], q[k:k + m], flags[k:k + m] = t_ns, run.p, run.v, run.q, unscored
        columns.n = k + m
        if unscored:
            return
        x = int(np.searchsorted(t_ns, self._next_cov_t))  # the first pose due for a covariance sample
        while x < m:
            t_x = int(t_ns[x])
            self._cov.append((t_x, run.p[x], run.q[x], run.pose_cov(x)))
            self._next_cov_t = t_x + self.cov_period_ns
            x += max(1, int(np.searchsorted(t_ns[x:], self._next_cov_t)))

    def trajectory(self) -> Trajectory:
        """Every pose in the order recorded."""
        return Trajectory(*self._columns.taken())

    def covariance_samples(self) -> CovarianceSamples:
        return CovarianceSamples.from_rows(self._cov)


@dataclass
class ReplayResult:
    estimator: Estimator
    trajectory: Trajectory
    covariances: CovarianceSamples
    sensors: list[str]
    wall_s: float
    duration_s: float
    notes: list[str] = field(default_factory=list)
    frames: list[FrameReport] = field(default_factory=list)  # one per camera frame fused or rejected
    extract_ms: list[float] = field(default_factory=list)  # feature extraction time per frame
    detector: str | None = None
    fusion_counts: dict = field(default_factory=dict)  # measurements refused by the fusion horizon
    faults: FaultInjector | None = None  # the faults played on the stream, with what each did
    health: dict = field(default_factory=dict)  # the estimator's health at the end (estimator.health)
    failures: dict = field(default_factory=dict)  # isolated failures of outputs and the trajectory file
    data_t0_ns: int = 0  # the first IMU sample: event times are counted from here
    smoothing: Any = None  # replay --smooth: a service.replay.smoothing.SmoothingResult
    extract_cpu_ms: list[float] = field(default_factory=list)  # as extract_ms, CPU time of the extracting thread
    incomplete: list[str] = field(default_factory=list)  # requested file outputs (an MCAP recording) not written in full
    kernels: KernelLoad | None = None  # how the estimator's kernels were had, before wall_s started


class FrameProcessor:
    """Camera work for the runtime: features in a worker thread, the update on the loop.

    The returned closure runs in fusion order, at the frame's own time; it keeps the per-frame
    report (and hands image, features and report to ``on_frame``, e.g. the overlay writer).
    ``keep``: how many recent reports to keep (None: all, for a replay's report; a live service
    flying for hours keeps a bounded window). With ``features.track_between`` the features of a
    frame depend on the frame before (optical flow): calls are then taken one at a time, and the
    runtime gives such a processor one worker (:attr:`in_order`), so they come in time order.
    """

    def __init__(self, options: FeatureOptions, expected_shape: tuple[int, int] | None,
                 on_frame: FrameCallback | None = None, keep: int | None = None) -> None:
        self.options = options
        self.expected_shape = expected_shape
        self.on_frame = on_frame
        self.reports: deque[FrameReport] = deque(maxlen=keep)
        self.extract_ms: deque[float] = deque(maxlen=keep)
        self.extract_cpu_ms: deque[float] = deque(maxlen=keep)
        self.extractor = FrameExtractor(options, expected_shape)
        self._extractor_lock = threading.Lock()

    @property
    def in_order(self) -> bool:
        """Frames must reach this processor one at a time, in time order (features tracked between detections)."""
        return self.extractor.in_order

    def __call__(self, frame: CameraFrame) -> Callable[[Estimator], FrameReport]:
        """On a camera worker thread: the features, and the update that fuses them."""
        if self.extractor.in_order:
            with self._extractor_lock:
                features = self.extractor(frame.image, frame.t_ns)
        else:
            features = self.extractor(frame.image, frame.t_ns)
        return self.fusing(frame, features)

    def fusing(self, frame: CameraFrame, features: FrameFeatures) -> Callable[[Estimator], FrameReport]:
        """The update for ``frame`` whose ``features`` were extracted elsewhere (a camera process)."""

        def fuse(est: Estimator) -> FrameReport:
            report = est.process_features(features)
            self.reports.append(report)
            self.extract_ms.append(features.extract_ms)
            self.extract_cpu_ms.append(features.extract_cpu_ms)
            if self.on_frame is not None:
                self.on_frame(frame.image, features, report)
            return report

        return fuse


def replay(
    dataset: Dataset,
    cfg: dict[str, Any],
    sensors: list[str] | None = None,
    on_progress: Callable[[float, float], None] | None = None,
    on_frame: FrameCallback | None = None,
    speed: float | None = None,
    trajectory_path: str | None = None,
    faults: Sequence[Fault] = (),
    fault_seed: int = 0,
    on_fused: Callable[[OutputPose], None] | None = None,
    start_at_s: float | None = None,
    prepare: Callable[[Any], None] | None = None,
    smoothing: SmoothingPlan | None = None,
) -> ReplayResult:
    """Run ``dataset`` through the runtime (as fast as possible unless ``speed`` > 0), ``faults`` played on its
    stream; ``start_at_s``: joined that far into the recording, as a service restarted in flight.

    ``prepare(runtime)`` runs once the runtime is built (``replay --smooth`` hooks its fixed-lag poses there);
    ``smoothing``: who sees the filter's steps (``replay --smooth``'s step files, a benchmark's recorders)."""
    configured = config_sections(cfg).replay
    sensors = checked_sensors(sensors or configured.sensors)
    notes: list[str] = []
    lidar = lidar_summary(dataset.root)
    if lidar is not None:  # an extra stream the estimator does not fuse: said, not read
        notes.append(f"{lidar['stream']}: {lidar['lines']} returns of the {lidar['model']} passed through, not fused "
                     "(map them with `vtolpose map`)")
    for name in [s for s in sensors if s != "imu"]:
        reason = missing_sensor(dataset, name)
        if reason is not None:
            notes.append(f"{reason}: {WITHOUT[name]}")
            log.warning("%s: %s", dataset.root, notes[-1])
            sensors = [s for s in sensors if s != name]
    has_gps = "gps" in sensors
    processor = None
    if "camera" in sensors:
        cam = dataset.calibration.camera
        processor = FrameProcessor(feature_options(cfg), (cam.height, cam.width), on_frame)
        limit_blas_threads(1)  # idle BLAS threads would spin on the core feature extraction needs
    recorder = Recorder(int(1e9 / configured.nees_rate_hz), absolute_position=has_gps)
    imu_t = dataset.imu_raw().t_ns
    if len(imu_t) == 0:
        raise ValueError(f"{dataset.root}: the IMU stream has no valid samples")
    span_s = (int(imu_t[-1]) - int(imu_t[0])) * 1e-9
    progress = None
    if on_progress is not None:
        on_progress(0.0, span_s)

        def progress(done_s: float) -> None:
            on_progress(done_s, span_s)
    injector = FaultInjector(faults, fault_seed) if faults else None
    kernels = load_compiled_kernels()  # compiled or loaded before the clock starts: never in wall_s
    wall0 = time.perf_counter()
    summary, runtime = run_replay(
        dataset, cfg, sensors=sensors, speed=speed, trajectory_path=trajectory_path,
        camera_processor=processor, handle_signals=False, faults=injector, on_progress=progress, start_at_s=start_at_s,
        prepare=prepare, smoothing=smoothing,
        on_fused=recorder.record if on_fused is None else lambda pose: (recorder.record(pose), on_fused(pose)),
        on_fused_run=recorder.record_run if on_fused is None else None,
    )
    wall = time.perf_counter() - wall0
    bug = runtime.failures.first("handling")
    if bug is not None:  # the live service carries on past it; an offline replay is a test and says so
        raise bug
    if on_progress is not None:
        on_progress(span_s, span_s)
    fusion_counts = {k: v for k, v in runtime.fusion.counts_report().items() if v["rejected"]}
    return ReplayResult(
        runtime.est, recorder.trajectory(), recorder.covariance_samples(), sensors, wall, summary.data_s, notes,
        list(processor.reports) if processor else [], list(processor.extract_ms) if processor else [],
        processor.options.detector if processor else None, fusion_counts, injector, summary.status.get("health", {}),
        summary.status.get("failures", {}), int(imu_t[0]),
        extract_cpu_ms=list(processor.extract_cpu_ms) if processor else [],
        incomplete=list(summary.incomplete), kernels=kernels,
    )


WITHOUT = {"gps": "position is inertial dead reckoning from the origin and will drift",
           "camera": "camera frames are not used"}


def missing_sensor(dataset: Dataset, sensor: str) -> str | None:
    """Why ``dataset`` cannot feed ``sensor`` ("gps" or "camera"), or None when it can."""
    if sensor == "gps":
        if dataset.gps() is None:
            return "no GPS stream (mav0/gps0/data.csv) in the dataset"
    elif sensor == "camera":
        if not dataset.has_camera:
            return "no camera stream (mav0/cam0/data.csv) in the dataset"
        if dataset.calibration.camera is None:
            return "no camera calibration in dataset.yaml"
        if not dataset.camera_frames():
            return "the camera index (mav0/cam0/data.csv) lists no valid frames"
    return None
