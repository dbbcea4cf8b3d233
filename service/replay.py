"""Offline replay: a dataset's streams merged in time order and fed to the estimator.

The recorder keeps the filtered pose after every IMU step (the trajectory written in TUM
format) and, at a lower rate, the pose covariance for the consistency (NEES) check.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from drivers.dataset import Dataset, GpsSeries, ImuSeries
from estimator.filter import Estimator
from estimator.measurements import GpsFix
from service.wiring import filter_options

log = logging.getLogger(__name__)

SENSOR_NAMES = ("imu", "gps", "camera")
KIND_IMU, KIND_GPS = 0, 1


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

    def __init__(self, capacity: int, cov_period_ns: int) -> None:
        self.t = np.zeros(capacity, dtype=np.int64)
        self.p = np.zeros((capacity, 3))
        self.v = np.zeros((capacity, 3))
        self.q = np.zeros((capacity, 4))
        self.n = 0
        self.cov_period_ns = cov_period_ns
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
        if s.t_ns >= self._next_cov_t and est.position_initialized:
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


def merge_order(imu_t: np.ndarray, gps_t: np.ndarray | None) -> tuple[list[int], list[int]]:
    """Kinds and indices of all samples in time order; at equal times the IMU goes first."""
    if gps_t is None or len(gps_t) == 0:
        return [KIND_IMU] * len(imu_t), list(range(len(imu_t)))
    times = np.concatenate([imu_t, gps_t])
    kinds = np.concatenate([np.zeros(len(imu_t), np.int8), np.ones(len(gps_t), np.int8)])
    index = np.concatenate([np.arange(len(imu_t)), np.arange(len(gps_t))])
    order = np.lexsort((kinds, times))
    return kinds[order].tolist(), index[order].tolist()


def replay(
    dataset: Dataset,
    cfg: dict[str, Any],
    sensors: list[str] | None = None,
    on_progress: Callable[[float, float], None] | None = None,
) -> ReplayResult:
    """Run the estimator over ``dataset`` as fast as possible."""
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
    if len(imu.t_ns) == 0:
        raise ValueError(f"{dataset.root}: the IMU stream has no valid samples")
    calibration = dataset.calibration
    est = Estimator(calibration, filter_options(cfg, calibration.imu.noise))
    recorder = Recorder(len(imu.t_ns), int(1e9 / cfg["replay.nees_rate_hz"]))
    kinds, indices = merge_order(imu.t_ns, gps.t_ns if gps is not None else None)
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
        else:
            est.process_gps(GpsFix(int(gps.t_ns[i]), gps.p_ned[i], float(gps.sigma_h[i]), float(gps.sigma_v[i])))
    wall = time.perf_counter() - wall0
    if on_progress is not None:
        on_progress(total_s, total_s)
    return ReplayResult(est, recorder.trajectory(), recorder.covariance_samples(), sensors, wall, total_s, notes)
