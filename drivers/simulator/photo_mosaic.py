"""Ground textures made of real photographs: a mosaic of recorded camera frames.

Why: scikit-image's samples are a handful of clean close-ups; frames a real camera recorded
(a room's walls and clutter, a hand-held walk) have the blur, noise, flat patches and repeated
structure a feature tracker meets in use. The frames are read on first use only, so nothing is
loaded, and nothing fails, until a flight actually draws them.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np


@dataclass(frozen=True, slots=True)
class PhotoSource:
    """Frames to lay out as ``tiles`` (rows, columns), picked evenly from ``folder/pattern`` by name."""

    name: str
    folder: Path
    pattern: str
    tiles: tuple[int, int] = (3, 3)

    def missing(self) -> str | None:
        """Why the frames cannot be read, or None when they can."""
        if not self.folder.is_dir():
            return f"{self.name}: no folder {self.folder}"
        found = sum(1 for _ in self.folder.glob(self.pattern))
        if found < self.tiles[0] * self.tiles[1]:
            return f"{self.name}: {found} frames ({self.pattern}) in {self.folder}, need {self.tiles[0] * self.tiles[1]}"
        return None


def shared_photo_sources(data_root: Path) -> dict[str, PhotoSource]:
    """The recordings in the shared data folder whose frames make floor textures, by texture name."""
    return {
        "v101": PhotoSource("v101", data_root / "euroc_dev" / "V101" / "mav0" / "cam0" / "data", "*.png"),
        "handheld": PhotoSource("handheld", data_root / "realsense_handheld" / "mav0" / "cam0" / "data", "*.jpg"),
    }


@lru_cache(maxsize=4)
def photo_mosaic(source: PhotoSource) -> np.ndarray:
    """The frames side by side, grey float32, each tile normalised to mean 0 and std 1.

    Every other tile is mirrored so that the mosaic's edges, which wrap onto each other, and the
    seams between tiles do not line up into one long straight edge.
    """
    import cv2  # on first use: a process that never draws a frame never loads OpenCV

    reason = source.missing()
    if reason is not None:
        raise FileNotFoundError(reason)
    files = sorted(source.folder.glob(source.pattern))
    rows, cols = source.tiles
    picks = np.linspace(0, len(files) - 1, rows * cols).round().astype(int)
    tiles: list[np.ndarray] = []
    size: tuple[int, int] | None = None
    for k, index in enumerate(picks):
        image = cv2.imread(str(files[index]), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise ValueError(f"{source.name}: cannot read {files[index]}")
        size = size or (image.shape[1], image.shape[0])
        tile = cv2.resize(image, size, interpolation=cv2.INTER_AREA).astype(np.float32)
        tile = (tile - tile.mean()) / max(float(tile.std()), 1e-6)
        tiles.append(tile[:, ::-1] if (k // cols + k % cols) % 2 else tile)
    return np.vstack([np.hstack(tiles[r * cols:(r + 1) * cols]) for r in range(rows)])
