"""Typed, timestamped samples: what drivers produce and the estimator consumes.

Times are integer nanoseconds on one monotonic clock; values are SI and already in the body
(FRD) or local world (NED) frame, so nothing downstream knows about devices or units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterator

import numpy as np


@dataclass(slots=True)
class ImuSample:
    """One IMU reading in body FRD: angular rate [rad/s] and specific force [m/s^2].

    A value, never changed once made; not a frozen dataclass only because one of those costs three
    times as much to construct, and one is made for every sample.
    """

    t_ns: int
    gyro: np.ndarray
    accel: np.ndarray


@dataclass(frozen=True, slots=True)
class ImuBatch:
    """Consecutive IMU readings handed over at once (a replay as fast as possible): the rows are
    :class:`ImuSample` s in time order, ``t_ns`` (n,) int64, ``gyro`` and ``accel`` (n, 3)."""

    t_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    def __len__(self) -> int:
        return len(self.t_ns)

    def samples(self) -> Iterator[ImuSample]:
        for t, gyro, accel in zip(self.t_ns.tolist(), self.gyro, self.accel):
            yield ImuSample(t, gyro, accel)


@dataclass(frozen=True, slots=True)
class ImuRange:
    """The largest angular rate [rad/s] and specific force [m/s^2] the IMU measures on any of its axes.

    A reading beyond it is no motion but a damaged sample (a flipped bit, a unit error, a corrupt
    row): integrated for even one step it can turn the attitude over, so it is refused instead.
    Samples arrive in body axes, rotated from the sensor's by its mounting, so the test is on the
    vector's length, which no rotation changes: at most √3 × the per-axis range.
    """

    gyro: float
    accel: float

    def exceeded(self, gyro: np.ndarray, accel: np.ndarray) -> bool:
        """True for a finite reading beyond the range (a non-finite one is counted as such elsewhere)."""
        gx, gy, gz = gyro.tolist()
        ax, ay, az = accel.tolist()
        g2, a2 = gx * gx + gy * gy + gz * gz, ax * ax + ay * ay + az * az
        return (g2 > 3.0 * self.gyro**2 or a2 > 3.0 * self.accel**2) and math.isfinite(g2 + a2)


def readings_finite(gyro: np.ndarray, accel: np.ndarray) -> bool:
    """Every component of both readings finite (their squares' sum is finite exactly then).

    On plain floats: for a 3-vector a numpy dot product costs several times the arithmetic, and
    this runs more than once for every IMU sample.
    """
    gx, gy, gz = gyro.tolist()
    ax, ay, az = accel.tolist()
    return math.isfinite(gx * gx + gy * gy + gz * gz + ax * ax + ay * ay + az * az)


def rows_finite(gyro: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """:func:`readings_finite` for each row of (n, 3) readings, the same arithmetic (compiled, one call)."""
    return screened(gyro, accel, None)[1]


def screened(gyro: np.ndarray, accel: np.ndarray, limits: ImuRange | None) -> tuple[np.ndarray, np.ndarray]:
    """(:meth:`ImuRange.exceeded`, :func:`readings_finite`) for each row of (n, 3) readings, with their
    arithmetic, in one compiled pass
    (``inertial.sample_kernel.screen_rows``, imported here: the samples' module stays below the others)."""
    from vtolpose.estimator.inertial.sample_kernel import screen_rows

    if limits is None:
        return screen_rows(gyro, accel, math.inf, math.inf)
    return screen_rows(gyro, accel, 3.0 * limits.gyro**2, 3.0 * limits.accel**2)


@dataclass(frozen=True, slots=True)
class GpsFix:
    """A position fix of the GPS antenna in local NED [m] with its 1-sigma errors [m]."""

    t_ns: int
    p_ned: np.ndarray
    sigma_h: float
    sigma_v: float


@dataclass(frozen=True, slots=True)
class CameraFrame:
    """A grey image (uint8, rows × cols) taken at ``t_ns`` (mid-exposure, host clock)."""

    t_ns: int
    image: np.ndarray
    seq: int = 0


@dataclass(frozen=True, slots=True)
class TruthSample:
    """Reference pose for scoring. ``q`` is None when the reference has no orientation."""

    t_ns: int
    p: np.ndarray
    q: np.ndarray | None = None
    v: np.ndarray | None = None


@dataclass(slots=True)
class RejectionCounts:
    """Per-sensor counters of what came in and what was used; reported, never dropped silently."""

    received: int = 0
    used: int = 0
    rejected: dict[str, int] = field(default_factory=dict)
    flagged: dict[str, int] = field(default_factory=dict)  # used, but worth knowing (e.g. a gap bridged)

    def reject(self, reason: str, n: int = 1) -> None:
        self.rejected[reason] = self.rejected.get(reason, 0) + n

    def flag(self, reason: str, n: int = 1) -> None:
        self.flagged[reason] = self.flagged.get(reason, 0) + n

    def as_dict(self) -> dict:
        out = {"received": self.received, "used": self.used, "rejected": dict(sorted(self.rejected.items()))}
        if self.flagged:
            out["flagged"] = dict(sorted(self.flagged.items()))
        return out
