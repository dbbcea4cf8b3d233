"""One flight mapped with several trajectories, next to the map the true poses give (``vtolpose demo --lidar``).

For each sensor set the demo maps the three poses a mapper can have (docs/smoothing.md): the
causal filter's, the fixed-lag history's (what a live mapper gets ~2-3 s late, as the daemon
computes it during the replay) and the smoothed one after the flight.
"""

from __future__ import annotations

from vtolpose.client import PoseWindow
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.files.lidar import LIDAR_CSV, LidarReturns
from vtolpose.service.mapping.mapper import pose_errors, true_ground
from vtolpose.service.mapping.poses import trajectory_window, truth_window, window_poses
from vtolpose.service.mapping.report import MappedFlight, map_and_score, table_lines
from vtolpose.service.replay.session import ReplayResult

# A cell that holds a few returns of the scenario's scanner: the landfill's survey scanner puts
# returns 0.2-0.8 m apart from 45 m up; the URG-04LX a few millimetres apart from under a metre.
MAP_CELL_M = {"landfill": 1.0, "book": 0.02}


def map_side_by_side(dataset: Dataset, trajectories: dict[str, PoseWindow], cell_m: float,
                     base_up_m: float = 0.0) -> tuple[list[MappedFlight], list[str]]:
    """The true-pose map, then one map per trajectory (in the order given), and the table that compares them."""
    returns = dataset.lidar()
    if returns is None:
        raise FileNotFoundError(f"{dataset.root / LIDAR_CSV}: no LIDAR returns to map")
    ground = true_ground(returns)
    truth = truth_window(dataset)
    sources = {"true poses": window_poses(truth)}
    sources.update({label: window_poses(window) for label, window in trajectories.items()})
    maps = [map_and_score(label, returns, source, cell_m, base_up_m, ground) for label, source in sources.items()]
    lines = [f"LIDAR map ({returns.spec.model}, {len(returns)} returns, {cell_m:g} m cells), "
             "each against the true ground:", *table_lines(maps)]
    if trajectories:
        lines += ["", "the poses at the returns' times against the truth (a map's volume error is about its height",
                  "error's mean over the map's cells × its area; the mean over the returns weighs a cell by how many it holds):",
                  *pose_error_lines(trajectories, truth, returns, cell_m, maps[1:])]
    return maps, lines


def pose_error_lines(trajectories: dict[str, PoseWindow], truth: PoseWindow, returns: LidarReturns, cell_m: float,
                     maps: list[MappedFlight]) -> list[str]:
    """Each trajectory's height error mean over the map's cells and over the returns, RMS, horizontal and
    attitude RMS, and the volume its mean over the cells explains."""
    width = max(len(label) for label in trajectories)
    lines = [f"  {'poses':<{width}}  {'height mean m':>13}  {'over returns':>12}  {'RMS m':>6}  {'horiz. RMS m':>12}  "
             f"{'att. RMS °':>10}  {'mean × area m³':>14}"]
    for (label, window), flight in zip(trajectories.items(), maps):
        e = pose_errors(window, truth, returns, cell_m)
        if not e:
            continue
        lines.append(f"  {label:<{width}}  {e['height_error_mean_m']:>+13.3f}  {e['height_error_mean_returns_m']:>+12.3f}  "
                     f"{e['height_error_rms_m']:>6.3f}  "
                     f"{e['horizontal_rms_m']:>12.3f}  {e['attitude_rms_deg']:>10.3f}  "
                     f"{e['height_error_mean_m'] * flight.score.area_m2:>+14.0f}")
    return lines


def pose_kinds(result: ReplayResult) -> dict[str, PoseWindow]:
    """A smoothed replay's (``replay_smoothed``) trajectories for mapping, by kind: filter, fixed lag, smoothed."""
    sm = result.smoothing
    if sm is None:
        raise ValueError("the replay was not smoothed: run it with replay_smoothed")
    kinds = {"filter": result.trajectory, f"fixed lag {sm.lag_s:g} s": sm.fixed_lag, "smoothed": sm.smoothed}
    return {kind: trajectory_window(t.t_ns, t.p, t.q) for kind, t in kinds.items()}
