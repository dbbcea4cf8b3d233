"""A height map that grows with the surveyed area: the mean height of the returns in each cell.

Cells are ``cell_m`` squares on the local NED frame's north/east axes: cell ``(i, j)`` holds the
points with ``floor(n / cell_m) == i`` and ``floor(e / cell_m) == j``. Storage is a dictionary of
square tiles created as returns reach them, so memory follows the area flown over, not its
bounding box, and nothing needs to know the area in advance. Points are added scan by scan in
arrival order; the same points in the same order give bit-identical sums, whoever placed them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TILE = 64  # cells per tile side
_PACK, _HALF = 1 << 32, 1 << 31


@dataclass(frozen=True, slots=True)
class HeightMap:
    """A dense snapshot: ``height`` [m up] and ``count`` (rows north, columns east); NaN where empty.

    Row ``r`` is north index ``i0 + r``, column ``c`` east index ``j0 + c``.
    """

    cell_m: float
    i0: int
    j0: int
    height: np.ndarray
    count: np.ndarray

    @property
    def covered(self) -> np.ndarray:
        return self.count > 0

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """North and east cell-centre coordinates [m] of every cell (two arrays shaped like ``height``)."""
        rows, cols = self.height.shape
        n = (self.i0 + np.arange(rows) + 0.5) * self.cell_m
        e = (self.j0 + np.arange(cols) + 0.5) * self.cell_m
        return np.meshgrid(n, e, indexing="ij")

    def extent(self) -> tuple[float, float, float, float]:
        """(east min, east max, north min, north max) of the grid's outer edges [m]."""
        rows, cols = self.height.shape
        return (self.j0 * self.cell_m, (self.j0 + cols) * self.cell_m,
                self.i0 * self.cell_m, (self.i0 + rows) * self.cell_m)


class HeightGrid:
    """Accumulates world points into per-cell height sums and counts."""

    def __init__(self, cell_m: float) -> None:
        if not (np.isfinite(cell_m) and cell_m > 0.0):
            raise ValueError(f"map cell size must be a positive number of metres, got {cell_m}")
        self.cell_m = float(cell_m)
        self._sum: dict[tuple[int, int], np.ndarray] = {}
        self._count: dict[tuple[int, int], np.ndarray] = {}
        self.points = 0

    def add(self, points_ned: np.ndarray) -> int:
        """Add NED points (N, 3); non-finite ones are ignored. Returns how many were added."""
        points = np.asarray(points_ned, dtype=float).reshape(-1, 3)
        points = points[np.all(np.isfinite(points), axis=1)]
        if not len(points):
            return 0
        i = np.floor(points[:, 0] / self.cell_m).astype(np.int64)
        j = np.floor(points[:, 1] / self.cell_m).astype(np.int64)
        up = -points[:, 2]
        ti, tj = np.floor_divide(i, TILE), np.floor_divide(j, TILE)
        local = (i - ti * TILE) * TILE + (j - tj * TILE)
        packed = ti * _PACK + (tj + _HALF)  # one integer per tile (tile indices stay far within ±2^31)
        tiles, which = np.unique(packed, return_inverse=True)
        for k, code in enumerate(tiles.tolist()):
            mask = which == k
            a = code // _PACK
            key = (a, code - a * _PACK - _HALF)
            if key not in self._sum:
                self._sum[key] = np.zeros(TILE * TILE)
                self._count[key] = np.zeros(TILE * TILE, dtype=np.int64)
            self._sum[key] += np.bincount(local[mask], weights=up[mask], minlength=TILE * TILE)
            self._count[key] += np.bincount(local[mask], minlength=TILE * TILE)
        self.points += len(points)
        return len(points)

    def snapshot(self) -> HeightMap:
        """The map so far as dense arrays over the tiles touched (empty: a 0 x 0 map)."""
        if not self._sum:
            return HeightMap(self.cell_m, 0, 0, np.zeros((0, 0)), np.zeros((0, 0), dtype=np.int64))
        keys = np.array(list(self._sum))
        t_lo, t_hi = keys.min(axis=0), keys.max(axis=0)
        shape = ((t_hi - t_lo + 1) * TILE).tolist()
        total, count = np.zeros(shape), np.zeros(shape, dtype=np.int64)
        for (a, b), s in self._sum.items():
            r, c = (a - t_lo[0]) * TILE, (b - t_lo[1]) * TILE
            total[r:r + TILE, c:c + TILE] = s.reshape(TILE, TILE)
            count[r:r + TILE, c:c + TILE] = self._count[(a, b)].reshape(TILE, TILE)
        rows, cols = np.flatnonzero(count.any(axis=1)), np.flatnonzero(count.any(axis=0))
        r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
        total, count = total[r0:r1, c0:c1], count[r0:r1, c0:c1]
        height = np.full(total.shape, np.nan)
        height[count > 0] = total[count > 0] / count[count > 0]
        return HeightMap(self.cell_m, int(t_lo[0] * TILE + r0), int(t_lo[1] * TILE + c0), height, count)
