"""Offline replay: a dataset's streams merged in time order and fed to the estimator.

The recorder keeps the filtered pose after every IMU step (the trajectory written in TUM
format) and, at a lower rate, the pose covariance for the consistency (NEES) check. Camera
frames are loaded and their features extracted when their turn comes (synchronously: the
replay's speed figure includes the extraction), then fused by ``Estimator.process_features``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from drivers.dataset import Dataset, GpsSeries, ImuSeries
from estimator.camera_pipeline import FrameReport
from estimator.features import FeatureOptions, FrameFeatures, extract_features
from estimator.filter import Estimator
from estimator.measurements import GpsFix
from service.threads import limit_blas_threads
from service.wiring import feature_options, filter_options

log = logging.getLogger(__name__)

SENSOR_NAMES = ("imu", "gps", "camera")
KIND_IMU, KIND_GPS, KIND_CAMERA = 0, 1, 2

# Called after each frame with the image (None if unreadable), its features and what the filter did.
FrameCallback = Callable[[np.ndarray | None, FrameFeatures, FrameReport], None]


@dataclass
class Trajectory:
    t_ns: np.ndarray
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray


@dataclass
class CovarianceSamples:
    """Pose covariance ([δp, δθ], 6 × 6) sampled at a low rate, with the pose it belongs to."""

    t_ns: np.ndarray
    p: np.ndarray
    q: np.ndarray
    cov: np.ndarray


class Recorder:
    """Preallocated per-IMU-step storage: no per-sample allocations on the hot path."""

    def __init__(self, capacity: int, cov_period_ns: int, absolute_position: bool = True) -> None:
        self.t = np.zeros(capacity, dtype=np.int64)
        self.p = np.zeros((capacity, 3))
        self.v = np.zeros((capacity, 3))
        self.q = np.zeros((capacity, 4))
        self.n = 0
        self.cov_period_ns = cov_period_ns
        # Without an absolute position source the start is the origin and the covariance is
        # meaningful from the first step; with one, only once the position is initialised.
        self.absolute_position = absolute_position
        self._next_cov_t = 0
        self._cov: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []

    def record(self, est: Estimator) -> None:
        """Keep the state if it advanced (the filter steps at its own rate, not every sample)."""
        s = est.state
        k = self.n
        if k and s.t_ns <= self.t[k - 1]:
            return
        self.t[k] = s.t_ns
        self.p[k] = s.p
        self.v[k] = s.v
        self.q[k] = s.q
        self.n = k + 1
        if s.t_ns >= self._next_cov_t and (est.position_initialized or not self.absolute_position):
            self._cov.append((s.t_ns, s.p.copy(), s.q.copy(), s.pose_covariance()))
            self._next_cov_t = s.t_ns + self.cov_period_ns

    def trajectory(self) -> Trajectory:
        n = self.n
        return Trajectory(self.t[:n].copy(), self.p[:n].copy(), self.v[:n].copy(), self.q[:n].copy())

    def covariance_samples(self) -> CovarianceSamples:
        if not self._cov:
            return CovarianceSamples(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 6, 6)))
        t, p, q, c = zip(*self._cov)
        return CovarianceSamples(np.array(t, dtype=np.int64), np.array(p), np.array(q), np.array(c))


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


def merge_order(
    imu_t: np.ndarray, gps_t: np.ndarray | None, camera_t: np.ndarray | None = None
) -> tuple[list[int], list[int]]:
    """Kinds and indices of all samples in time order; at equal times IMU, then GPS, then camera."""
    streams = [(KIND_IMU, imu_t), (KIND_GPS, gps_t), (KIND_CAMERA, camera_t)]
    streams = [(k, np.asarray(t, dtype=np.int64)) for k, t in streams if t is not None and len(t)]
    if len(streams) == 1:
        return [KIND_IMU] * len(imu_t), list(range(len(imu_t)))
    times = np.concatenate([t for _, t in streams])
    kinds = np.concatenate([np.full(len(t), k, np.int8) for k, t in streams])
    index = np.concatenate([np.arange(len(t)) for _, t in streams])
    order = np.lexsort((kinds, times))
    return kinds[order].tolist(), index[order].tolist()


class FrameSource:
    """Frames of a dataset, loaded and reduced to features one at a time, in order."""

    def __init__(self, dataset: Dataset, options: FeatureOptions) -> None:
        self.dataset = dataset
        self.options = options
        self.index = dataset.camera_frames()
        cam = dataset.calibration.camera
        self.expected_shape = (cam.height, cam.width) if cam is not None else None

    @property
    def times(self) -> np.ndarray:
        return np.array([t for t, _ in self.index], dtype=np.int64)

    def features(self, i: int) -> tuple[np.ndarray | None, FrameFeatures]:
        t_ns, path = self.index[i]
        image = self.dataset.load_frame(path)
        if image is None:
            return None, FrameFeatures.rejected(t_ns, self.expected_shape or (0, 0), "unreadable")
        return image, extract_features(image, t_ns, self.options, self.expected_shape)


def replay(
    dataset: Dataset,
    cfg: dict[str, Any],
    sensors: list[str] | None = None,
    on_progress: Callable[[float, float], None] | None = None,
    on_frame: FrameCallback | None = None,
) -> ReplayResult:
    """Run the estimator over ``dataset`` as fast as possible; ``on_frame`` sees every camera frame."""
    sensors = list(sensors or cfg["replay.sensors"])
    unknown = [s for s in sensors if s not in SENSOR_NAMES]
    if unknown:
        raise ValueError(f"unknown sensor(s) {unknown}; choose from {', '.join(SENSOR_NAMES)}")
    if "imu" not in sensors:
        raise ValueError("the estimator needs the IMU: include 'imu' in the sensors")
    notes: list[str] = []
    imu: ImuSeries = dataset.imu()
    gps: GpsSeries | None = dataset.gps() if "gps" in sensors else None
    if "gps" in sensors and gps is None:
        notes.append("no GPS stream in the dataset: position is inertial dead reckoning from the origin and will drift")
        log.warning("%s: %s", dataset.root, notes[-1])
    frames = _frame_source(dataset, cfg, notes) if "camera" in sensors else None
    limit_blas_threads(1)
    if len(imu.t_ns) == 0:
        raise ValueError(f"{dataset.root}: the IMU stream has no valid samples")
    calibration = dataset.calibration
    est = Estimator(calibration, filter_options(cfg, calibration.imu.noise))
    recorder = Recorder(len(imu.t_ns), int(1e9 / cfg["replay.nees_rate_hz"]), absolute_position=gps is not None)
    kinds, indices = merge_order(imu.t_ns, gps.t_ns if gps is not None else None, frames.times if frames else None)
    reports: list[FrameReport] = []
    extract_ms: list[float] = []
    imu_t = imu.t_ns.tolist()
    gyro, accel = imu.gyro, imu.accel
    t_first = imu_t[0]
    total_s = (imu_t[-1] - t_first) * 1e-9
    process_imu, record = est.process_imu, recorder.record
    wall0 = time.perf_counter()
    for n, (kind, i) in enumerate(zip(kinds, indices)):
        if kind == KIND_IMU:
            if process_imu(imu_t[i], gyro[i], accel[i]) and est.state is not None:
                record(est)
            if on_progress is not None and n % 2000 == 0:
                on_progress((imu_t[i] - t_first) * 1e-9, total_s)
        elif kind == KIND_GPS:
            est.process_gps(GpsFix(int(gps.t_ns[i]), gps.p_ned[i], float(gps.sigma_h[i]), float(gps.sigma_v[i])))
        else:
            image, features = frames.features(i)
            report = est.process_features(features)
            reports.append(report)
            extract_ms.append(features.extract_ms)
            if on_frame is not None:
                on_frame(image, features, report)
    wall = time.perf_counter() - wall0
    if on_progress is not None:
        on_progress(total_s, total_s)
    return ReplayResult(est, recorder.trajectory(), recorder.covariance_samples(), sensors, wall, total_s, notes,
                        reports, extract_ms, frames.options.detector if frames else None)


def _frame_source(dataset: Dataset, cfg: dict[str, Any], notes: list[str]) -> FrameSource | None:
    """The camera stream, or None with a note saying why there is none."""
    if dataset.calibration.camera is None:
        notes.append("no camera calibration in dataset.yaml: camera frames are not used")
    elif not dataset.has_camera:
        notes.append("no camera stream (mav0/cam0/data.csv) in the dataset: the camera is not used")
    else:
        source = FrameSource(dataset, feature_options(cfg))
        if len(source.index):
            return source
        notes.append("the camera index lists no valid frames: the camera is not used")
    log.warning("%s: %s", dataset.root, notes[-1])
    return None
