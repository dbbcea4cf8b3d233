"""The mapper's loop: scan by scan, every return placed with its own pose, into one height grid."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import numpy as np

from vtolpose.client import OutsideHistory, PoseWindow
from vtolpose.drivers.files.lidar import LidarReturns
from vtolpose.drivers.simulator import make_scenario
from vtolpose.estimator import (
    GroundFunction, HeightGrid, LidarMount, mean_over_cells, place_returns, quat_from_euler, quat_to_rot,
    rotation_angle,
)
from vtolpose.service.mapping.poses import PoseSource

log = logging.getLogger(__name__)


@dataclass
class MapRun:
    """The grid and what happened to the scans: placed, outside the poses, not reached before the wait ran out."""

    grid: HeightGrid
    scans: int = 0
    scans_placed: int = 0
    returns_placed: int = 0
    scans_outside: int = 0
    returns_outside: int = 0
    scans_not_reached: int = 0
    wall_s: float = 0.0
    stopped: str | None = None  # why the run ended before the last scan

    def counts(self) -> dict:
        return {"scans": self.scans, "scans_placed": self.scans_placed, "returns_placed": self.returns_placed,
                "scans_outside_poses": self.scans_outside, "returns_outside_poses": self.returns_outside,
                "scans_not_reached": self.scans_not_reached, "wall_s": round(self.wall_s, 3)}


def map_returns(returns: LidarReturns, poses: PoseSource, cell_m: float, time_offset_ns: int = 0) -> MapRun:
    """Place every scan's returns with ``poses`` (one call per scan) and grid them at ``cell_m``.

    ``time_offset_ns`` is added to the LIDAR's stamps to put them on the poses' clock.
    """
    run = MapRun(HeightGrid(cell_m))
    mount = returns.spec.mount
    bounds = returns.scan_bounds()
    run.scans = len(bounds)
    started = time.perf_counter()
    for k, (a, b) in enumerate(bounds.tolist()):
        t = returns.t_ns[a:b] + time_offset_ns
        try:
            p, q = poses(t)
        except OutsideHistory:
            run.scans_outside += 1
            run.returns_outside += b - a
            continue
        except TimeoutError as exc:
            run.scans_not_reached = run.scans - k
            run.stopped = str(exc)
            log.warning("mapping stopped at scan %d of %d: %s", k, run.scans, exc)
            break
        run.returns_placed += run.grid.add(place_returns(p, q, mount, returns.angle[a:b], returns.range_m[a:b]))
        run.scans_placed += 1
    run.wall_s = time.perf_counter() - started
    return run


def with_boresight(returns: LidarReturns, roll_deg: float, pitch_deg: float, yaw_deg: float) -> LidarReturns:
    """The returns with their scanner turned by a boresight correction (Z-Y-X angles about the body axes)."""
    turn = quat_to_rot(quat_from_euler(*np.radians([roll_deg, pitch_deg, yaw_deg])))
    mount = LidarMount(turn @ returns.spec.mount.R_BL, returns.spec.mount.t_BL)
    return replace(returns, spec=replace(returns.spec, mount=mount))


def true_ground(returns: LidarReturns) -> GroundFunction | None:
    """The ground the returns were simulated against (named in ``lidar0/sensor.yaml``), or None for a real flight."""
    if returns.ground_scenario is None:
        return None
    return make_scenario(returns.ground_scenario).ground_height


def pose_errors(estimate: PoseWindow, truth: PoseWindow, returns: LidarReturns, cell_m: float,
                time_offset_ns: int = 0) -> dict:
    """The estimate's pose errors at the returns' times (where both cover them), up positive (a map raised by it).

    ``height_error_mean_m`` is the mean over the map's cells (``cell_m``, the returns placed with
    the estimate, as its map places them) of each cell's mean error: what the map's volume error
    follows (a cell's height is the mean of its returns; the volume sums cells, not returns).
    ``height_error_mean_returns_m`` is the plain mean over the returns, for comparison: a climb or a
    slow pass packs many returns into few cells and weighs in it far beyond its area. RMS heights,
    horizontal and attitude errors are over the returns."""
    t_ns = returns.t_ns + time_offset_ns
    inside = (t_ns >= max(estimate.t_ns[0], truth.t_ns[0])) & (t_ns <= min(estimate.t_ns[-1], truth.t_ns[-1]))
    t = t_ns[inside]
    if not t.size:
        return {}
    p_e, q_e = estimate.interpolate(t)
    p_t, q_t = truth.interpolate(t)
    d = p_e - p_t
    up_error = -d[:, 2]
    placed = place_returns(p_e, q_e, returns.spec.mount, returns.angle[inside], returns.range_m[inside])
    cell_mean, cells = mean_over_cells(placed, up_error, cell_m)
    return {
        "returns": int(t.size),
        "cells": cells,
        "height_error_mean_m": cell_mean,
        "height_error_mean_returns_m": float(np.mean(up_error)),
        "height_error_rms_m": float(np.sqrt(np.mean(d[:, 2] ** 2))),
        "horizontal_rms_m": float(np.sqrt(np.mean(np.sum(d[:, :2] ** 2, axis=1)))),
        "attitude_rms_deg": float(np.degrees(np.sqrt(np.mean(rotation_angle(q_e, q_t) ** 2)))),
    }
