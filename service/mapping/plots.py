"""PNGs of a height map and of its error against the true ground (matplotlib, the ``plot`` extra)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vtolpose.estimator import HeightMap
from vtolpose.service.calibration.plots import _pyplot, _save


def plot_height(path: str | Path, hmap: HeightMap, title: str) -> Path:
    """The map's heights [m up], north up, east to the right."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 7))
    image = ax.imshow(hmap.height, origin="lower", extent=hmap.extent(), cmap="terrain", interpolation="nearest")
    fig.colorbar(image, ax=ax, label="height above the origin [m]")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_title(title)
    ax.set_aspect("equal")
    return _save(plt, fig, path)


def plot_error(path: str | Path, hmap: HeightMap, error: np.ndarray, title: str) -> Path:
    """Map height minus the true ground per cell, on a symmetric colour scale (99th percentile of |error|)."""
    plt = _pyplot()
    finite = error[np.isfinite(error)]
    limit = max(float(np.percentile(np.abs(finite), 99)), 1e-6) if finite.size else 1.0
    fig, ax = plt.subplots(figsize=(8, 7))
    image = ax.imshow(error, origin="lower", extent=hmap.extent(), cmap="RdBu_r", vmin=-limit, vmax=limit,
                      interpolation="nearest")
    fig.colorbar(image, ax=ax, label="map − true ground [m]")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_title(title)
    ax.set_aspect("equal")
    return _save(plt, fig, path)
