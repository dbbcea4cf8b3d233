"""Maps side by side: the same returns placed with different poses, scored against the true ground.

The true-pose map shows what the grid itself costs (range noise, slope within a cell); every
other map differs from it only by its poses. :func:`attribution_sources` splits one trajectory's
cost into its position, its attitude and, with true poses taken once per scan, what stamping
every return with its own time is worth.
"""

from __future__ import annotations

from dataclasses import dataclass

from vtolpose.client import PoseWindow
from vtolpose.drivers.files.lidar import LidarReturns
from vtolpose.estimator import GroundFunction, MapScore, score_map
from vtolpose.service.mapping.mapper import MapRun, map_returns
from vtolpose.service.mapping.poses import PoseSource, mixed_poses, one_pose_per_scan, window_poses


@dataclass
class MappedFlight:
    label: str
    run: MapRun
    score: MapScore

    def as_dict(self) -> dict:
        return {"label": self.label, **self.run.counts(), **self.score.as_dict()}


def map_and_score(label: str, returns: LidarReturns, poses: PoseSource, cell_m: float, base_up_m: float,
                  ground: GroundFunction | None, time_offset_ns: int = 0) -> MappedFlight:
    run = map_returns(returns, poses, cell_m, time_offset_ns)
    return MappedFlight(label, run, score_map(run.grid.snapshot(), base_up_m, ground))


def attribution_sources(estimate: PoseWindow, truth: PoseWindow, name: str = "trajectory") -> dict[str, PoseSource]:
    """The maps that split a trajectory's cost: its position alone, its attitude alone, and return timing."""
    return {
        "true poses": window_poses(truth),
        name: window_poses(estimate),
        f"{name}: position only (true attitude)": mixed_poses(estimate, truth),
        f"{name}: attitude only (true position)": mixed_poses(truth, estimate),
        "true poses, one per scan (no per-return time)": one_pose_per_scan(truth),
    }


def _num(value: float | None, fmt: str) -> str:
    return "n/a" if value is None else format(value, fmt)


def score_lines(score: MapScore) -> list[str]:
    """One map's figures for people."""
    lines = [f"  {score.cells} cells of {score.cell_m:g} m ({score.area_m2:.0f} m²), {score.returns} returns "
             f"({score.returns_per_cell:.1f} per cell), coverage {100 * score.coverage:.1f} % inside the outline",
             f"  volume above {score.base_up_m:g} m: {score.volume_m3:.6g} m³"]
    if score.true_volume_m3 is not None:
        lines[-1] += (f" (true {score.true_volume_m3:.6g} m³, error {score.volume_error_m3:+.4g} m³ = "
                      f"{_num(score.volume_error_percent, '+.2f')} %)")
        lines.append(f"  height vs true ground: RMSE {score.height_rmse_m:.3f} m, bias {score.height_bias_m:+.3f} m, "
                     f"95 % of cells within {score.height_error_p95_m:.3f} m")
    return lines


def table_lines(maps: list[MappedFlight]) -> list[str]:
    """The maps side by side: height RMSE and bias, volume and its error."""
    width = max(len(m.label) for m in maps)
    head = f"  {'map':<{width}}  {'cells':>7}  {'RMSE m':>7}  {'bias m':>7}  {'volume m³':>11}  {'error m³':>9}  {'error %':>7}"
    lines = [head]
    for m in maps:
        s = m.score
        lines.append(f"  {m.label:<{width}}  {s.cells:>7d}  {_num(s.height_rmse_m, '7.3f')}  {_num(s.height_bias_m, '+7.3f')}  "
                     f"{s.volume_m3:>11.6g}  {_num(s.volume_error_m3, '+9.4g')}  {_num(s.volume_error_percent, '+7.2f')}")
    truth = next((m.score.true_volume_m3 for m in maps if m.score.true_volume_m3 is not None), None)
    if truth is not None:
        lines.append(f"  (true volume above {maps[0].score.base_up_m:g} m over the covered cells: {truth:.6g} m³; "
                     "each map is scored on its own cells)")
    return lines
