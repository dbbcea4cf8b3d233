"""What a height map is worth: height error against the true ground, volume above a base, coverage.

- **Height RMSE**: per covered cell, the map's height (mean of its returns) against the true
  ground's mean height over that cell (``subsamples`` × ``subsamples`` points), so a sloping
  cell is compared with what it should average to, not with its centre.
- **Volume** above a horizontal base at ``base_up_m`` [m up in the local frame]: the sum over
  covered cells of ``cell area × max(height − base, 0)``. The true volume is the same integral of
  the true ground over the same cells. Volume error = mapped − true; the two use the same cells,
  so it measures what the map got wrong, not what it did not see.
- **A pose's height error as the volume sees it**: the mean over the map's cells of each cell's
  mean error (:func:`mean_over_cells`), not the mean over the returns: a cell counts its area
  once however many returns fell in it, so a climb that packs its returns into a few cells
  weighs what those cells weigh in the volume, no more.
- **Coverage**: the covered area, and the fraction of the cells inside the map's outline (the
  covered cells with their enclosed holes filled) that hold a return: 1.0 means no holes.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np
from scipy import ndimage

from vtolpose.estimator.mapping.height_grid import HeightMap

# ground_height(n, e) -> down coordinate of the ground [m], arrays broadcast alike (the simulator's scenarios).
GroundFunction = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True, slots=True)
class MapScore:
    """A height map's figures; the truth-dependent ones are None without a true ground."""

    cell_m: float
    cells: int
    area_m2: float
    returns: int
    returns_per_cell: float
    coverage: float
    base_up_m: float
    volume_m3: float
    true_volume_m3: float | None = None
    volume_error_m3: float | None = None
    volume_error_percent: float | None = None
    height_rmse_m: float | None = None
    height_bias_m: float | None = None
    height_error_p95_m: float | None = None

    def as_dict(self) -> dict:
        return asdict(self)


def true_cell_means(hmap: HeightMap, ground_down: GroundFunction, base_up_m: float,
                    subsamples: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Per cell of ``hmap``: the true ground's mean height [m up] and mean height above the base (clipped at 0)."""
    if subsamples < 1:
        raise ValueError(f"subsamples must be at least 1, got {subsamples}")
    n, e = hmap.centres()
    offsets = ((np.arange(subsamples) + 0.5) / subsamples - 0.5) * hmap.cell_m
    up = np.zeros(n.shape)
    above = np.zeros(n.shape)
    for dn in offsets:
        for de in offsets:
            h = -np.asarray(ground_down(n + dn, e + de), dtype=float)
            up += h
            above += np.maximum(h - base_up_m, 0.0)
    k = subsamples * subsamples
    return up / k, above / k


def height_error(hmap: HeightMap, ground_down: GroundFunction, subsamples: int = 4) -> np.ndarray:
    """Map height minus true mean height per cell [m]; NaN where the map is empty."""
    true_up, _ = true_cell_means(hmap, ground_down, 0.0, subsamples)
    return hmap.height - true_up


def mean_over_cells(points_ned: np.ndarray, values: np.ndarray, cell_m: float) -> tuple[float, int]:
    """``(mean over cells of the per-cell mean of values, cells)``: each point's value goes to the
    cell its ``points_ned`` row falls in (the height grid's cells); points with a non-finite
    coordinate or value are left out, as the grid leaves them out. ``(nan, 0)`` for no points."""
    points = np.asarray(points_ned, dtype=float).reshape(-1, 3)
    values = np.asarray(values, dtype=float).reshape(-1)
    if len(points) != len(values):
        raise ValueError(f"mean_over_cells: {len(points)} points but {len(values)} values")
    keep = np.all(np.isfinite(points), axis=1) & np.isfinite(values)
    if not np.any(keep):
        return float("nan"), 0
    i = np.floor(points[keep, 0] / cell_m).astype(np.int64)
    j = np.floor(points[keep, 1] / cell_m).astype(np.int64)
    _, cell = np.unique(np.stack([i, j], axis=1), axis=0, return_inverse=True)
    cell = cell.reshape(-1)
    sums = np.bincount(cell, weights=values[keep])
    counts = np.bincount(cell)
    return float(np.mean(sums / counts)), int(len(counts))


def coverage_fraction(covered: np.ndarray) -> float:
    """Covered cells over the cells inside the outline (covered ones plus the holes they enclose)."""
    if not covered.any():
        return 0.0
    outline = ndimage.binary_fill_holes(covered)
    return float(covered.sum() / outline.sum())


def score_map(hmap: HeightMap, base_up_m: float = 0.0, ground_down: GroundFunction | None = None,
              subsamples: int = 4) -> MapScore:
    """The figures of ``hmap``; with ``ground_down`` (the true ground) also its errors."""
    covered = hmap.covered
    cells = int(covered.sum())
    area = hmap.cell_m * hmap.cell_m
    heights = hmap.height[covered]
    volume = float(area * np.sum(np.maximum(heights - base_up_m, 0.0)))
    returns = int(hmap.count.sum())
    figures = dict(
        cell_m=hmap.cell_m, cells=cells, area_m2=cells * area, returns=returns,
        returns_per_cell=returns / cells if cells else 0.0, coverage=coverage_fraction(covered),
        base_up_m=float(base_up_m), volume_m3=volume,
    )
    if ground_down is None or cells == 0:
        return MapScore(**figures)
    true_up, true_above = true_cell_means(hmap, ground_down, base_up_m, subsamples)
    err = heights - true_up[covered]
    true_volume = float(area * np.sum(true_above[covered]))
    return MapScore(
        **figures, true_volume_m3=true_volume, volume_error_m3=volume - true_volume,
        volume_error_percent=100.0 * (volume - true_volume) / true_volume if true_volume > 0 else None,
        height_rmse_m=float(np.sqrt(np.mean(err**2))), height_bias_m=float(np.mean(err)),
        height_error_p95_m=float(np.percentile(np.abs(err), 95)),
    )
