"""Whole-stream sample series (numpy arrays): what datasets, importers and the simulator exchange."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _rows(a: np.ndarray | None, n: int, cols: int, what: str) -> np.ndarray | None:
    """``a`` as float64 (n × cols), or a ValueError saying which field has the wrong shape."""
    if a is None:
        return None
    a = np.asarray(a, dtype=np.float64)
    shape = (n, cols) if cols else (n,)
    if a.shape != shape:
        raise ValueError(f"{what}: expected shape {shape}, got {a.shape}")
    return a


@dataclass(slots=True)
class ImuSeries:
    """IMU samples: angular rate [rad/s] and specific force [m/s²], N × 3, in the axes named by the caller."""

    t_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    def __post_init__(self) -> None:
        self.t_ns = np.asarray(self.t_ns, dtype=np.int64).reshape(-1)
        n = len(self.t_ns)
        self.gyro, self.accel = _rows(self.gyro, n, 3, "ImuSeries.gyro"), _rows(self.accel, n, 3, "ImuSeries.accel")


@dataclass(slots=True)
class GpsSeries:
    """Antenna fixes in local NED [m] with per-axis 1-σ horizontal / vertical errors [m].

    ``origin_lla`` is the geodetic point the NED frame is centred on, when known.
    """

    t_ns: np.ndarray
    p_ned: np.ndarray
    sigma_h: np.ndarray
    sigma_v: np.ndarray
    origin_lla: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        self.t_ns = np.asarray(self.t_ns, dtype=np.int64).reshape(-1)
        n = len(self.t_ns)
        self.p_ned = _rows(self.p_ned, n, 3, "GpsSeries.p_ned")
        # Scalars are accepted for constant sigmas; copies keep the arrays writable and contiguous.
        self.sigma_h = _rows(np.array(np.broadcast_to(self.sigma_h, (n,))), n, 0, "GpsSeries.sigma_h")
        self.sigma_v = _rows(np.array(np.broadcast_to(self.sigma_v, (n,))), n, 0, "GpsSeries.sigma_v")


@dataclass(slots=True)
class TruthSeries:
    """Reference trajectory of the body point ``point_b`` (world NED); q body→world, w first.

    ``q``/``v`` are None for position-only truth; biases (body axes) are None when unknown.
    """

    t_ns: np.ndarray
    p: np.ndarray
    q: np.ndarray | None = None
    v: np.ndarray | None = None
    bias_g: np.ndarray | None = None
    bias_a: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.t_ns = np.asarray(self.t_ns, dtype=np.int64).reshape(-1)
        n = len(self.t_ns)
        self.p = _rows(self.p, n, 3, "TruthSeries.p")
        self.q = _rows(self.q, n, 4, "TruthSeries.q")
        self.v = _rows(self.v, n, 3, "TruthSeries.v")
        self.bias_g = _rows(self.bias_g, n, 3, "TruthSeries.bias_g")
        self.bias_a = _rows(self.bias_a, n, 3, "TruthSeries.bias_a")
