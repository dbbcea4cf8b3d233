"""``vtolpose export``: a TUM trajectory as a WGS84 flight path for the survey team (GeoJSON, KML).

The TUM file (``replay --out`` or ``run --out``) holds local NED positions; they become WGS84
around the origin the replay used: ``--origin``, else the dataset's (``--dataset``: its GPS
origin, or its first fix), else the origin stored in the ``--quality`` recording.

Quality per point: a TUM file has none, so it comes from an MCAP recording of the same run
(``--mcap FILE`` on ``replay`` or ``run``), whose ``/vtolpose/pose`` channel holds every
published estimate. Each point takes the estimate at its own time stamp (the nearest within
``MATCH_NS``) and carries its ``quality`` (0–100, the ODOMETRY/status figure), ``sigma_h_m``
(the 1-σ semi-major axis of the horizontal position covariance), ``sigma_v_m`` and ``status``.
Without a recording these are null, and the file says so (``quality_source``).
"""

from __future__ import annotations

import argparse
import logging
import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

log = logging.getLogger(__name__)

MATCH_NS = 20_000_000  # a recorded estimate this close to a trajectory stamp is that point's


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="a TUM trajectory as a WGS84 flight path with time and quality per point (GeoJSON, KML)",
        description=(__doc__ or "").split("\n", 1)[1] + "\nExample:\n"
        "  vtolpose replay data/landfill --out traj.txt --mcap flight.mcap\n"
        "  vtolpose export traj.txt --dataset data/landfill --quality flight.mcap --geojson path.geojson --kml path.kml",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("trajectory", metavar="TRAJ.txt", help="TUM trajectory in local NED (what replay --out writes)")
    p.add_argument("--geojson", metavar="OUT", help="write GeoJSON here")
    p.add_argument("--kml", metavar="OUT", help="write KML here")
    p.add_argument("--dataset", metavar="DIR", help="the dataset the trajectory was made from (its NED origin)")
    p.add_argument("--origin", metavar="LAT,LON,ALT", help="the NED origin, WGS84 degrees and metres")
    p.add_argument("--quality", metavar="REC.mcap", help="MCAP recording of the same run (--mcap): quality per point")
    p.add_argument("--step", type=float, default=0.1, metavar="S",
                   help="keep one pose every S seconds (default 0.1; 0 keeps every pose)")
    p.set_defaults(run=run)


def _origin(args: argparse.Namespace, recorded_origin) -> tuple[tuple[float, float, float], str]:
    if args.origin:
        try:
            lat, lon, alt = (float(x) for x in args.origin.split(","))
        except ValueError:
            raise ValueError(f"--origin {args.origin!r}: expected LAT,LON,ALT (degrees, degrees, metres)") from None
        if not (abs(lat) <= 90.0 and abs(lon) <= 180.0 and math.isfinite(alt)):
            raise ValueError(f"--origin {args.origin!r}: latitude within ±90°, longitude within ±180°")
        return (lat, lon, alt), "--origin"
    if args.dataset:
        from vtolpose.drivers.files.dataset import Dataset

        dataset = Dataset.open(args.dataset)
        gps = dataset.gps()
        origin = gps.origin_lla if gps is not None else dataset.calibration.gps.origin_lla
        if origin is not None:
            return tuple(map(float, origin)), f"dataset {args.dataset}"
        raise ValueError(f"--dataset {args.dataset}: no geodetic origin (its GPS is local NED and dataset.yaml has no gps.origin); "
                         "give --origin LAT,LON,ALT")
    if recorded_origin is not None:
        return tuple(map(float, recorded_origin)), f"recording {args.quality}"
    raise ValueError("the trajectory is local NED: give --dataset DIR or --origin LAT,LON,ALT (or a --quality recording that has one)")


def _thinned(t_ns: np.ndarray, step_s: float) -> np.ndarray:
    """Indices keeping one pose per ``step_s`` (the first at or after each step), and always the last."""
    import numpy as np

    if step_s <= 0.0:
        return np.arange(len(t_ns))
    slots = (t_ns - t_ns[0]) // int(step_s * 1e9)
    keep = np.flatnonzero(np.r_[True, np.diff(slots) > 0])
    return keep if keep[-1] == len(t_ns) - 1 else np.r_[keep, len(t_ns) - 1]


def run(args: argparse.Namespace) -> int:
    import numpy as np
    import pymap3d

    from vtolpose.drivers.files.csvio import seconds_text
    from vtolpose.drivers.files.survey import SurveyPath, read_recorded_estimates, write_geojson, write_kml
    from vtolpose.drivers.files.tum import read_tum

    if not args.geojson and not args.kml:
        raise ValueError("nothing to write: give --geojson OUT and/or --kml OUT")
    if args.step < 0.0 or not math.isfinite(args.step):
        raise ValueError(f"--step {args.step}: must be >= 0 seconds")
    t_ns, p_ned, _ = read_tum(args.trajectory)
    recorded = read_recorded_estimates(args.quality) if args.quality else None
    origin, origin_source = _origin(args, recorded.origin if recorded is not None else None)
    keep = _thinned(t_ns, args.step)
    t_ns, p_ned = t_ns[keep], p_ned[keep]
    lat, lon, alt = pymap3d.ned2geodetic(p_ned[:, 0], p_ned[:, 1], p_ned[:, 2], *origin)
    n = len(t_ns)
    quality, sigma_h, sigma_v, status = [None] * n, [None] * n, [None] * n, [None] * n
    matched = 0
    if recorded is not None:
        right = np.clip(np.searchsorted(recorded.t_ns, t_ns), 1, len(recorded.t_ns) - 1) if len(recorded.t_ns) > 1 else np.zeros(n, int)
        left = np.maximum(right - 1, 0)
        nearest = np.where(np.abs(recorded.t_ns[left] - t_ns) <= np.abs(recorded.t_ns[right] - t_ns), left, right)
        for i, j in enumerate(nearest.tolist()):
            if abs(int(recorded.t_ns[j]) - int(t_ns[i])) <= MATCH_NS:
                quality[i], status[i] = int(recorded.quality[j]), recorded.status[j]
                sigma_h[i], sigma_v[i] = float(recorded.sigma_h_m[j]), float(recorded.sigma_v_m[j])
                matched += 1
    about = {
        "trajectory": str(args.trajectory), "origin_lat_lon_alt": list(origin), "origin_source": origin_source,
        "height": "WGS84 ellipsoidal, metres",
        "quality_source": (f"{args.quality} /vtolpose/pose: quality 0-100 as MAVLink ODOMETRY; sigma_h_m the 1-sigma "
                           "semi-major axis of the horizontal position covariance; sigma_v_m the vertical 1-sigma")
        if recorded is not None else None,
    }
    path = SurveyPath([seconds_text(int(t)) for t in t_ns], np.atleast_1d(lat), np.atleast_1d(lon), np.atleast_1d(alt),
                      quality, sigma_h, sigma_v, status, about)
    if args.geojson:
        write_geojson(args.geojson, path)
    if args.kml:
        write_kml(args.kml, path)
    print(f"{n} points ({'all poses' if args.step <= 0 else f'one per {args.step:g} s'}), origin from {origin_source}; "
          f"quality: {f'{matched} of {n} points matched in {args.quality}' if recorded is not None else 'none (no --quality recording)'}")
    if recorded is not None and matched < n:
        log.warning("%d point(s) have no recorded estimate within %.0f ms: their quality is null", n - matched, MATCH_NS / 1e6)
    return 0
