"""What every GPS driver shares: geodetic → local NED, error sigmas from DOP, the reading type.

Sigmas handed to the estimator are 1-σ *per axis* (north, east; down). Receivers state a
horizontal error as a 2-D figure (HDOP × UERE, an accuracy radius), so it is split over the two
horizontal axes (÷ √2). Without a vertical figure, VDOP is taken as ``VDOP_PER_HDOP`` × HDOP,
the usual ratio for a sky-limited antenna.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pymap3d

from vtolpose.estimator.core.measurements import GpsFix

__all__ = ["GpsReading", "LocalNed", "VDOP_PER_HDOP", "dop_sigmas", "horizontal_per_axis"]

VDOP_PER_HDOP = 1.5


def horizontal_per_axis(radial_m: float) -> float:
    """Per-axis 1-σ from a 2-D horizontal error figure."""
    return radial_m / math.sqrt(2.0)


def dop_sigmas(hdop: float, vdop: float | None, uere_m: float) -> tuple[float, float]:
    """(sigma_h per axis, sigma_v) [m] from dilutions of precision and the user range error."""
    vdop = VDOP_PER_HDOP * hdop if vdop is None or vdop <= 0.0 else vdop
    return horizontal_per_axis(hdop * uere_m), vdop * uere_m


class LocalNed:
    """Geodetic → local NED around a fixed origin, or around the first position converted."""

    def __init__(self, origin: tuple[float, float, float] | None = None) -> None:
        if origin is not None:
            lat, lon, _ = origin
            if abs(lat) > 90.0 or abs(lon) > 180.0:
                raise ValueError(f"GPS origin {origin}: lat must be in [-90, 90], lon in [-180, 180] degrees")
            origin = tuple(float(x) for x in origin)
        self.origin: tuple[float, float, float] | None = origin

    def __call__(self, lat: float, lon: float, alt: float) -> np.ndarray:
        if self.origin is None:
            self.origin = (float(lat), float(lon), float(alt))
        return np.array(pymap3d.geodetic2ned(lat, lon, alt, *self.origin), dtype=float)


@dataclass(frozen=True, slots=True)
class GpsReading:
    """A fix as the estimator wants it (``fix``, local NED) and as recordings store it (geodetic)."""

    fix: GpsFix
    lat_deg: float
    lon_deg: float
    alt_m: float               # ellipsoidal height when the receiver gives it, else MSL
    sigma_source: str          # "GST" | "DOP" | "accuracy" (receiver's own estimate)
    satellites: int | None = None
    hdop: float | None = None
