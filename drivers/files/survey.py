"""A flight path for survey tools: GeoJSON (RFC 7946, the standard ``json`` module) and KML (``simplekml``).

Both files hold the same thing: the path as one line, and one point per pose with its time and
quality. Coordinates are WGS84 longitude, latitude and ellipsoidal height in metres (GeoJSON's
third coordinate; KML's ``absolute`` altitude, which viewers read as height above sea level, so a
path shows the local geoid height, tens of metres, too high or low in Google Earth).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import simplekml


@dataclass
class SurveyPath:
    """Per point: time [s, the trajectory's clock], WGS84 position, and the quality fields (None: unknown)."""

    t_s: list[str]  # exact decimal seconds as in the trajectory file
    lat: np.ndarray
    lon: np.ndarray
    alt: np.ndarray
    quality: list[int | None]
    sigma_h_m: list[float | None]
    sigma_v_m: list[float | None]
    status: list[str | None]
    about: dict[str, Any]  # where the path, its origin and its quality come from


def _point_properties(path: SurveyPath, i: int) -> dict[str, Any]:
    def rounded(x: float | None, digits: int) -> float | None:
        return None if x is None or not math.isfinite(x) else round(x, digits)

    return {"t_s": float(path.t_s[i]), "t": path.t_s[i], "quality": path.quality[i],
            "sigma_h_m": rounded(path.sigma_h_m[i], 4), "sigma_v_m": rounded(path.sigma_v_m[i], 4), "status": path.status[i]}


def write_geojson(out: str | Path, path: SurveyPath) -> None:
    """A FeatureCollection: the path as a LineString, then one Point per pose with time and quality."""
    coords = [[round(float(lo), 9), round(float(la), 9), round(float(h), 4)] for lo, la, h in zip(path.lon, path.lat, path.alt)]
    line = {"type": "Feature", "geometry": {"type": "LineString", "coordinates": coords},
            "properties": {"name": "flight path", "t_start_s": float(path.t_s[0]), "t_end_s": float(path.t_s[-1]), **path.about}}
    points = [{"type": "Feature", "geometry": {"type": "Point", "coordinates": c}, "properties": _point_properties(path, i)}
              for i, c in enumerate(coords)]
    doc = {"type": "FeatureCollection", "features": [line, *points]}
    Path(out).write_text(json.dumps(doc, indent=None, separators=(",", ":"), allow_nan=False) + "\n", encoding="utf-8")


_QUALITY_COLOURS = ((80, simplekml.Color.green), (50, simplekml.Color.yellow), (1, simplekml.Color.orange),
                    (0, simplekml.Color.red))


def _colour(quality: int | None) -> str:
    if quality is None:
        return simplekml.Color.gray
    return next(colour for floor, colour in _QUALITY_COLOURS if quality >= floor)


def write_kml(out: str | Path, path: SurveyPath) -> None:
    """The path as a LineString placemark, one point placemark per pose (coloured by quality) with time and
    quality in its ExtendedData, and where it all comes from in the document's description."""
    kml = simplekml.Kml(name="vtolpose flight")
    kml.document.description = "; ".join(f"{k}: {v}" for k, v in path.about.items())
    line = kml.newlinestring(name="flight path", coords=list(zip(path.lon.tolist(), path.lat.tolist(), path.alt.tolist())))
    line.altitudemode = simplekml.AltitudeMode.absolute
    line.style.linestyle.width = 2
    styles: dict[str, simplekml.Style] = {}
    folder = kml.newfolder(name="poses")
    for i in range(len(path.t_s)):
        props = _point_properties(path, i)
        point = folder.newpoint(name=path.t_s[i], coords=[(float(path.lon[i]), float(path.lat[i]), float(path.alt[i]))])
        point.altitudemode = simplekml.AltitudeMode.absolute
        for key in ("t_s", "quality", "sigma_h_m", "sigma_v_m", "status"):
            point.extendeddata.newdata(name=key, value="" if props[key] is None else str(props[key]))
        colour = _colour(path.quality[i])
        if colour not in styles:
            styles[colour] = simplekml.Style()
            styles[colour].iconstyle.color = colour
            styles[colour].iconstyle.scale = 0.4
        point.style = styles[colour]
    kml.save(str(out))


@dataclass
class RecordedEstimates:
    """Estimates read back from a recording: times, and per estimate quality, σ_h, σ_v and status."""

    t_ns: np.ndarray
    quality: np.ndarray
    sigma_h_m: np.ndarray
    sigma_v_m: np.ndarray
    status: list[str]
    origin: tuple[float, float, float] | None


def horizontal_vertical_sigma(cov6: np.ndarray) -> tuple[float, float]:
    """σ_h: the square root of the larger eigenvalue of the north/east position covariance (the 1-σ
    semi-major axis, so never optimistic in any direction); σ_v: the down standard deviation."""
    horizontal = np.linalg.eigvalsh(cov6[0:2, 0:2])
    return math.sqrt(max(float(horizontal[-1]), 0.0)), math.sqrt(max(float(cov6[2, 2]), 0.0))


def read_recorded_estimates(mcap_path: str | Path, topic: str = "/vtolpose/pose") -> RecordedEstimates:
    """The ``<prefix>/pose`` documents a ``--mcap`` recording holds on ``topic``, with its NED origin."""
    from mcap.reader import make_reader

    mcap_path = Path(mcap_path)
    if not mcap_path.is_file():
        raise FileNotFoundError(f"{mcap_path}: recording not found")
    t, quality, sigma_h, sigma_v, status, origin = [], [], [], [], [], None
    with mcap_path.open("rb") as f:
        reader = make_reader(f)
        for _schema, _channel, message in reader.iter_messages(topics=[topic]):
            doc = json.loads(message.data)
            cov = np.array([np.nan if c is None else c for c in doc["cov"]], dtype=float).reshape(6, 6)
            h, v = horizontal_vertical_sigma(cov) if np.all(np.isfinite(cov[0:3, 0:3])) else (math.nan, math.nan)
            t.append(int(doc["t_ns"]))
            quality.append(int(doc["quality"]))
            sigma_h.append(h)
            sigma_v.append(v)
            status.append(str(doc["status"]))
            if doc.get("origin"):
                origin = (doc["origin"]["lat"], doc["origin"]["lon"], doc["origin"]["alt"])
    if not t:
        raise ValueError(f"{mcap_path}: no estimates on {topic} (record them with --mcap FILE on replay or run)")
    order = np.argsort(t, kind="stable")
    return RecordedEstimates(np.array(t, np.int64)[order], np.array(quality)[order], np.array(sigma_h)[order],
                             np.array(sigma_v)[order], [status[i] for i in order], origin)
