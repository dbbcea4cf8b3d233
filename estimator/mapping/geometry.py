"""A line-scanning LIDAR's returns in the world: beam direction, mounting, the pose of each return.

The scanner's own axes L: the beams sweep the L x–y plane, at angle ``a`` from +x towards +y,
so a return at range ``r`` is ``r [cos a, sin a, 0]`` in L. ``R_BL`` maps L to body FRD and
``t_BL`` is the scanner's centre in the body. A return lands at ``p + R(q) (R_BL x_L + t_BL)``
with the body pose ``(p, q)`` *at that return's own time*: a scan sweeps for tens of
milliseconds while the vehicle moves and turns, so one pose per scan smears the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vtolpose.estimator.core.rotation import is_proper_rotation, quat_to_rot
from vtolpose.estimator.pose_history import PoseWindow


@dataclass(frozen=True, slots=True, eq=False)
class LidarMount:
    """Where the scanner sits on the body: ``R_BL`` (scanner axes → body FRD) and ``t_BL`` [m]."""

    R_BL: np.ndarray
    t_BL: np.ndarray

    def __post_init__(self) -> None:
        r = np.asarray(self.R_BL, dtype=float)
        t = np.asarray(self.t_BL, dtype=float)
        if r.shape != (3, 3) or not is_proper_rotation(r):
            raise ValueError(f"LIDAR R_BL must be a proper 3 x 3 rotation, got {np.array2string(r, precision=4)}")
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise ValueError(f"LIDAR t_BL must be 3 finite numbers, got {t.tolist()}")
        object.__setattr__(self, "R_BL", r)
        object.__setattr__(self, "t_BL", t)

    def __eq__(self, other: object) -> bool:
        return (isinstance(other, LidarMount) and np.array_equal(self.R_BL, other.R_BL)
                and np.array_equal(self.t_BL, other.t_BL))

    __hash__ = None  # type: ignore[assignment]  # equal by value, and arrays are not hashable


def beam_vectors(angle: np.ndarray) -> np.ndarray:
    """Unit beam directions (N, 3) in the scanner's axes for beam angles [rad]."""
    angle = np.asarray(angle, dtype=float).reshape(-1)
    return np.column_stack([np.cos(angle), np.sin(angle), np.zeros_like(angle)])


def returns_in_body(mount: LidarMount, angle: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    """Return points (N, 3) in body FRD."""
    points_l = beam_vectors(angle) * np.asarray(range_m, dtype=float).reshape(-1, 1)
    return points_l @ mount.R_BL.T + mount.t_BL


def place_returns(p: np.ndarray, q: np.ndarray, mount: LidarMount, angle: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    """World NED points (N, 3) of returns, each with its own body pose ``p`` (N, 3), ``q`` (N, 4, w first)."""
    body = returns_in_body(mount, angle, range_m)
    return np.asarray(p, dtype=float) + np.einsum("nij,nj->ni", quat_to_rot(np.asarray(q, dtype=float)), body)


def place_with_window(window: PoseWindow, t_ns: np.ndarray, mount: LidarMount, angle: np.ndarray,
                      range_m: np.ndarray) -> np.ndarray:
    """Returns placed with the window's poses interpolated at each return's time (OutsideHistory beyond it)."""
    p, q = window.interpolate(np.asarray(t_ns, dtype=np.int64))
    return place_returns(p, q, mount, angle, range_m)
