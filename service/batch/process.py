"""What a batch does with one flight, as library calls (no subprocess): the figures for its row.

In ``work`` (the flight's partial output folder) it writes ``trajectory-smoothed.txt`` and
``trajectory-filtered.txt`` (TUM), ``covariance-smoothed.csv``, ``report.json`` (what ``replay
--smooth --report`` writes) and, with LIDAR, ``map.json`` (what ``map --report`` writes, mapped
with the smoothed poses) and ``map-height.png``. An EuRoC folder or a bag is imported into
``work/dataset`` first and removed at the end (``vtolpose import`` keeps one).
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.files.tum import write_tum
from vtolpose.estimator import height_error, OutputPose
from vtolpose.service.batch.flights import FlightInput
from vtolpose.service.batch.settings import BatchSettings
from vtolpose.service.commands.common import write_json
from vtolpose.service.mapping.mapper import pose_errors, true_ground
from vtolpose.service.mapping.poses import trajectory_window, truth_window, window_poses
from vtolpose.service.mapping.report import map_and_score
from vtolpose.service.replay.report import build_report
from vtolpose.service.replay.session import Trajectory
from vtolpose.service.replay.smoothing import replay_smoothed
from vtolpose.service.runtime.status import pose_quality
from vtolpose.service.runtime.wiring import config_sections

QUALITY_BINS = 60  # at most this many quality figures per flight in the table, whatever its length
QUALITY_MIN_BIN_S = 10.0


class QualityTrack:
    """The output quality (0-100, as the pose messages carry it) per fused pose, summed per second of the flight."""

    def __init__(self) -> None:
        self.t0_ns: int | None = None
        self.sums: list[float] = []
        self.counts: list[int] = []
        self.usable = 0

    def add(self, pose: OutputPose) -> None:
        if self.t0_ns is None:
            self.t0_ns = pose.t_ns
        k = max(0, (pose.t_ns - self.t0_ns) // 1_000_000_000)
        while len(self.sums) <= k:
            self.sums.append(0.0)
            self.counts.append(0)
        quality = pose_quality(pose)
        self.sums[k] += quality
        self.counts[k] += 1
        self.usable += quality > 0

    def summary(self) -> dict[str, Any]:
        """Mean quality, the share of poses usable (quality > 0), and the means over at most QUALITY_BINS
        equal bins of a whole number of 10 s."""
        sums, counts = np.array(self.sums), np.array(self.counts)
        total = int(counts.sum())
        if not total:
            return {"quality_mean": None, "quality_usable_fraction": None, "quality_bin_s": None, "quality_over_time": []}
        width = int(QUALITY_MIN_BIN_S * max(1, math.ceil(len(sums) / QUALITY_BINS / QUALITY_MIN_BIN_S)))
        bins = [(sums[a:a + width].sum(), counts[a:a + width].sum()) for a in range(0, len(sums), width)]
        return {"quality_mean": round(float(sums.sum() / total), 2),
                "quality_usable_fraction": round(self.usable / total, 4),
                "quality_bin_s": float(width),
                "quality_over_time": [round(float(s / c), 1) if c else None for s, c in bins]}


def _imported(flight: FlightInput, settings: BatchSettings, work: Path) -> Path:
    """The flight as a dataset folder: itself, or imported into ``work/dataset``."""
    if flight.kind == "dataset":
        return Path(flight.path)
    target = work / "dataset"
    if flight.kind == "euroc":
        from vtolpose.drivers.files.euroc_import import import_euroc

        e = settings.euroc
        import_euroc(flight.path, target, gps_rate_hz=e.gps_rate_hz, gps_sigma_m=e.gps_sigma_m, seed=e.seed,
                     mounting=e.mounting, camera=e.camera)
    elif flight.kind == "rosbag":
        from vtolpose.drivers.files.rosbag_import import import_rosbag

        b = settings.bag
        if not b.imu_topic or not b.gps_topic:
            raise ValueError(f"{flight.path}: a bag needs --imu-topic TOPIC and --gps-topic TOPIC to be imported")
        import_rosbag(flight.path, target, b.imu_topic, b.gps_topic, b.image_topic, b.truth_topic, b.calibration,
                      b.fix_sigma)
    else:
        raise ValueError(f"{flight.path}: unknown kind of recording {flight.kind!r}")
    return target


def path_length_m(traj: Trajectory, step_s: float = 1.0) -> float | None:
    """Distance flown along the usable poses, sampled every ``step_s`` (the noise of single steps left out)."""
    valid = traj.valid
    if np.count_nonzero(valid) < 2:
        return None
    t, p = traj.t_ns[valid], traj.p[valid]
    marks = np.searchsorted(t, np.arange(t[0], t[-1] + 1, int(step_s * 1e9)))
    marks = np.unique(np.append(marks[marks < len(t)], len(t) - 1))
    return float(np.sum(np.linalg.norm(np.diff(p[marks], axis=0), axis=1)))


def _round(value: Any, digits: int = 4) -> Any:
    return round(float(value), digits) if isinstance(value, (int, float, np.floating)) and value is not None else value


def process_flight(flight: FlightInput, settings: BatchSettings, work: Path) -> dict[str, Any]:
    """Replay (smoothed), score, map; write the files into ``work``; return the row's figures."""
    dataset_path = _imported(flight, settings, work)
    try:
        dataset = Dataset.open(dataset_path)
        cfg = settings.cfg
        sensors = list(settings.sensors or config_sections(cfg).replay.sensors)
        quality = QualityTrack()
        result = replay_smoothed(dataset, cfg, work / "trajectory-smoothed.txt", work / "covariance-smoothed.csv",
                                 sensors=sensors, on_fused=quality.add)
        write_tum(work / "trajectory-filtered.txt", result.trajectory.t_ns, result.trajectory.p, result.trajectory.q)
        report = build_report(result, dataset, cfg, settings.score_from_s)
        write_json(work / "report.json", report)
        row = _replay_figures(report, result)
        row.update(quality.summary())
        row.update(_map_figures(dataset, result.smoothing.smoothed, settings, work))
        return row
    finally:
        if dataset_path != Path(flight.path):
            shutil.rmtree(dataset_path, ignore_errors=True)


def _replay_figures(report: dict, result) -> dict[str, Any]:
    gps = report["sensors"].get("gps", {})
    smoothing = report.get("smoothing") or {}
    return {
        "duration_s": _round(report["duration_s"], 3),
        "distance_m": _round(path_length_m(result.smoothing.smoothed), 2),
        "resets": int(report["reset_counter"]),
        "sensors": ",".join(report["sensor_set"]),
        "gps_received": int(gps.get("received", 0)),
        "gps_rejected": int(sum(gps.get("rejected", {}).values())),
        "truth": report["truth"],
        "position_rmse_m": _round(report.get("position_rmse_m")),
        "smoothed_position_rmse_m": _round(smoothing.get("smoothed", {}).get("position_rmse_m")),
        "attitude_rmse_deg": _round(report.get("attitude_rmse_deg")),
        "notes": len(report["notes"]),
    }


MAP_COLUMNS = ("map_cells", "map_area_m2", "map_coverage", "volume_m3", "true_volume_m3", "volume_error_m3",
               "volume_error_percent", "map_height_rmse_m", "map_height_bias_m", "pose_height_error_cells_m",
               "pose_height_error_returns_m")


def _map_figures(dataset: Dataset, smoothed: Trajectory, settings: BatchSettings, work: Path) -> dict[str, Any]:
    """The LIDAR map with the smoothed poses (None figures without LIDAR); the pose's height error
    over the map's cells where the dataset has truth."""
    figures: dict[str, Any] = dict.fromkeys(MAP_COLUMNS)
    returns = dataset.lidar()
    valid = smoothed.valid
    if returns is None or np.count_nonzero(valid) < 2:
        return figures
    window = trajectory_window(smoothed.t_ns[valid], smoothed.p[valid], smoothed.q[valid])
    ground = true_ground(returns)
    flight = map_and_score("smoothed", returns, window_poses(window), settings.cell_m, settings.base_up_m, ground)
    s = flight.score
    figures.update(map_cells=s.cells, map_area_m2=_round(s.area_m2, 1), map_coverage=_round(s.coverage),
                   volume_m3=_round(s.volume_m3, 2), true_volume_m3=_round(s.true_volume_m3, 2),
                   volume_error_m3=_round(s.volume_error_m3, 2), volume_error_percent=_round(s.volume_error_percent),
                   map_height_rmse_m=_round(s.height_rmse_m), map_height_bias_m=_round(s.height_bias_m))
    doc: dict[str, Any] = {"dataset": str(dataset.root), "lidar": returns.spec.model, "map": flight.as_dict()}
    if dataset.truth() is not None:
        errors = pose_errors(window, truth_window(dataset), returns, settings.cell_m)
        if errors:
            doc["pose_errors"] = errors
            figures.update(pose_height_error_cells_m=_round(errors["height_error_mean_m"]),
                           pose_height_error_returns_m=_round(errors["height_error_mean_returns_m"]))
    write_json(work / "map.json", doc)
    if settings.plots:
        from vtolpose.service.mapping.plots import plot_error, plot_height  # matplotlib, only to draw

        hmap = flight.run.grid.snapshot()
        plot_height(work / "map-height.png", hmap, f"{dataset.meta['name']}: height map (smoothed poses)")
        if ground is not None:
            plot_error(work / "map-error.png", hmap, height_error(hmap, ground),
                       f"{dataset.meta['name']}: map − true ground (smoothed poses)")
    return figures
