"""One flight mapped with several trajectories, next to the map the true poses give (``vtolpose demo --lidar``)."""

from __future__ import annotations

from vtolpose.client import PoseWindow
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.files.lidar import LIDAR_CSV
from vtolpose.service.mapping.mapper import true_ground
from vtolpose.service.mapping.poses import truth_window, window_poses
from vtolpose.service.mapping.report import MappedFlight, map_and_score, table_lines

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
    sources = {"true poses": window_poses(truth_window(dataset))}
    sources.update({label: window_poses(window) for label, window in trajectories.items()})
    maps = [map_and_score(label, returns, source, cell_m, base_up_m, ground) for label, source in sources.items()]
    lines = [f"LIDAR map ({returns.spec.model}, {len(returns)} returns, {cell_m:g} m cells), "
             "each against the true ground:", *table_lines(maps)]
    return maps, lines
