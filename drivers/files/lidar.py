"""A line-scanning LIDAR in a dataset: ``mav0/lidar0/data.csv`` (one line per return) and ``sensor.yaml``.

Every return has its own time, because a scan sweeps for tens of milliseconds while the vehicle
moves: ``#timestamp [ns],scan [],angle [rad],range [m]``. ``scan`` numbers the sweeps (the lines
of one scan are consecutive), ``angle`` is the beam in the scanner's x–y plane from +x towards
+y, ``range`` the measured distance. Beams that saw nothing (beyond the maximum range, into the
sky) have no line. ``sensor.yaml`` describes the scanner (field of view, angular step, scan rate,
range noise and limits) and its mounting on the body (``R_BL``, ``t_BL``; see
``vtolpose.estimator.mapping.geometry``). A simulated dataset also names the scenario whose
ground the returns were cast against (``ground_truth.scenario``), so a map can be scored.

Nothing here fuses the LIDAR: replay passes it by, the mapper (``vtolpose map``) reads it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import yaml

from vtolpose.drivers.files.calibration_yaml import CalibrationError, YamlReader, load_yaml_file
from vtolpose.drivers.files.csvio import read_numeric_csv, write_numeric_csv
from vtolpose.estimator.mapping.geometry import LidarMount

log = logging.getLogger(__name__)

LIDAR_CSV = "mav0/lidar0/data.csv"
LIDAR_SENSOR = "mav0/lidar0/sensor.yaml"
LIDAR_HEADER = "#timestamp [ns],scan [],angle [rad],range [m]"
LIDAR_FORMATS = ["%.0f", "%.7f", "%.4f"]
_SPEC_KEYS = {"sensor_type", "model", "fov_deg", "step_deg", "scan_rate_hz", "range_sigma_m", "range_sigma_fraction",
              "range_resolution_m", "min_range_m", "max_range_m", "R_BL", "t_BL", "ground_truth"}


@dataclass(frozen=True, slots=True)
class LidarSpec:
    """A spinning-mirror line scanner: one revolution per scan, beams every ``step_deg`` across ``fov_deg``.

    The beams are centred on the scanner's +x axis. Beam ``k`` of a scan is measured
    ``k · step / 360° / scan_rate`` after the first: the mirror turns at a constant rate, so the
    field of view is swept in ``fov / 360°`` of the scan period. Range noise is Gaussian with
    σ = max(``range_sigma_m``, ``range_sigma_fraction`` × range), rounded to ``range_resolution_m``.
    """

    model: str
    fov_deg: float
    step_deg: float
    scan_rate_hz: float
    range_sigma_m: float
    range_sigma_fraction: float
    range_resolution_m: float
    min_range_m: float
    max_range_m: float
    mount: LidarMount

    def __post_init__(self) -> None:
        def need(ok: bool, what: str, value: float) -> None:
            if not ok:
                raise ValueError(f"LIDAR {what}, got {value}")

        finite = all(np.isfinite(v) for v in (self.fov_deg, self.step_deg, self.scan_rate_hz, self.range_sigma_m,
                                               self.range_sigma_fraction, self.range_resolution_m,
                                               self.min_range_m, self.max_range_m))
        need(finite, "figures must be finite numbers", self)
        need(0.0 < self.fov_deg <= 360.0, "field of view must be in (0, 360] degrees", self.fov_deg)
        need(0.0 < self.step_deg <= self.fov_deg, "angular step must be positive and at most the field of view",
             self.step_deg)
        need(self.scan_rate_hz > 0.0, "scan rate must be positive", self.scan_rate_hz)
        need(self.range_sigma_m >= 0.0 and self.range_sigma_fraction >= 0.0, "range noise must be non-negative",
             self.range_sigma_m)
        need(self.range_resolution_m >= 0.0, "range resolution must be non-negative", self.range_resolution_m)
        need(0.0 <= self.min_range_m < self.max_range_m, "ranges must satisfy 0 <= min < max", self.max_range_m)

    @property
    def beams(self) -> int:
        """Beams per scan."""
        return int(np.floor(self.fov_deg / self.step_deg + 1e-9)) + 1

    def angles(self) -> np.ndarray:
        """Beam angles [rad] of one scan, in the order they are measured, centred on +x."""
        k = np.arange(self.beams)
        return np.radians((k - 0.5 * (self.beams - 1)) * self.step_deg)

    @property
    def beam_interval_s(self) -> float:
        """Time between two beams of a scan: the mirror's turn by one step."""
        return self.step_deg / 360.0 / self.scan_rate_hz

    @property
    def sweep_s(self) -> float:
        """Time from a scan's first beam to its last."""
        return (self.beams - 1) * self.beam_interval_s

    def range_sigma(self, range_m: np.ndarray) -> np.ndarray:
        return np.maximum(self.range_sigma_m, self.range_sigma_fraction * np.asarray(range_m, dtype=float))


@dataclass(slots=True)
class LidarReturns:
    """Every return of a flight, time-ordered, with the scanner that made them."""

    spec: LidarSpec
    t_ns: np.ndarray
    scan: np.ndarray
    angle: np.ndarray
    range_m: np.ndarray
    ground_scenario: str | None = None  # the simulated scenario whose ground was scanned
    skipped: int = field(default=0)

    def __post_init__(self) -> None:
        self.t_ns = np.asarray(self.t_ns, dtype=np.int64).reshape(-1)
        n = self.t_ns.size
        self.scan = np.asarray(self.scan, dtype=np.int64).reshape(-1)
        self.angle = np.asarray(self.angle, dtype=float).reshape(-1)
        self.range_m = np.asarray(self.range_m, dtype=float).reshape(-1)
        for name in ("scan", "angle", "range_m"):
            if getattr(self, name).size != n:
                raise ValueError(f"LidarReturns.{name}: {getattr(self, name).size} values for {n} times")

    def __len__(self) -> int:
        return int(self.t_ns.size)

    def scan_bounds(self) -> np.ndarray:
        """(K, 2) start/stop indices of the scans: runs of consecutive lines with one scan number."""
        if not len(self):
            return np.zeros((0, 2), dtype=np.int64)
        starts = np.flatnonzero(np.r_[True, np.diff(self.scan) != 0])
        return np.column_stack([starts, np.r_[starts[1:], len(self)]])

    def scans(self) -> Iterator[slice]:
        """One slice per scan, in time order."""
        for a, b in self.scan_bounds().tolist():
            yield slice(a, b)


def _spec_from_yaml(doc: Any, source: str) -> tuple[LidarSpec, str | None]:
    y = YamlReader(source)
    top = y.mapping(doc, "(top level)", _SPEC_KEYS, required=("fov_deg", "step_deg", "scan_rate_hz", "max_range_m",
                                                             "R_BL", "t_BL"))
    if top.get("sensor_type", "lidar") != "lidar":
        raise y.fail("sensor_type", "'lidar'", top["sensor_type"])
    number = {k: y.number(top.get(k, 0.0), k, non_negative=True)
              for k in ("fov_deg", "step_deg", "scan_rate_hz", "range_sigma_m", "range_sigma_fraction",
                        "range_resolution_m", "min_range_m", "max_range_m")}
    truth = y.mapping(top.get("ground_truth"), "ground_truth", {"scenario"})
    scenario = truth.get("scenario")
    if scenario is not None and not isinstance(scenario, str):
        raise y.fail("ground_truth.scenario", "a scenario name", scenario)
    try:
        spec = LidarSpec(model=str(top.get("model") or "lidar"), **number,
                         mount=LidarMount(y.rotation(top["R_BL"], "R_BL"), y.vector(top["t_BL"], "t_BL", 3)))
    except ValueError as exc:
        raise CalibrationError(f"{source}: {exc}") from None
    return spec, scenario


def lidar_sensor_yaml(spec: LidarSpec, ground_scenario: str | None = None) -> str:
    """``lidar0/sensor.yaml``: the scanner, its mounting and, for a simulated flight, the scanned ground."""
    doc: dict[str, Any] = {
        "sensor_type": "lidar", "model": spec.model, "fov_deg": float(spec.fov_deg), "step_deg": float(spec.step_deg),
        "scan_rate_hz": float(spec.scan_rate_hz), "range_sigma_m": float(spec.range_sigma_m),
        "range_sigma_fraction": float(spec.range_sigma_fraction), "range_resolution_m": float(spec.range_resolution_m),
        "min_range_m": float(spec.min_range_m), "max_range_m": float(spec.max_range_m),
        "R_BL": (spec.mount.R_BL + 0.0).tolist(), "t_BL": (spec.mount.t_BL + 0.0).tolist(),
    }
    if ground_scenario is not None:
        doc["ground_truth"] = {"scenario": ground_scenario}
    head = ("# lidar0/data.csv: one line per return at its own time: scan number, beam angle in the scanner's\n"
            "# x-y plane from +x towards +y [rad], range [m]. R_BL maps the scanner's axes to body FRD;\n"
            "# t_BL is its centre in the body [m].\n")
    return head + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120)


def write_lidar(root: str | Path, returns: LidarReturns) -> None:
    """Write ``mav0/lidar0/data.csv`` and ``sensor.yaml`` under the dataset folder ``root``."""
    root = Path(root)
    values = np.column_stack([returns.scan.astype(float), returns.angle, returns.range_m])
    write_numeric_csv(root / LIDAR_CSV, LIDAR_HEADER, returns.t_ns, values, LIDAR_FORMATS)
    (root / LIDAR_SENSOR).write_text(lidar_sensor_yaml(returns.spec, returns.ground_scenario), encoding="utf-8",
                                     newline="\n")


def read_lidar_spec(root: str | Path) -> tuple[LidarSpec, str | None]:
    """The scanner and its mounting from ``mav0/lidar0/sensor.yaml`` (and the simulated ground's scenario)."""
    path = Path(root) / LIDAR_SENSOR
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found (it gives the LIDAR's mounting, R_BL and t_BL)")
    return _spec_from_yaml(load_yaml_file(path), str(path))


def read_lidar(root: str | Path) -> LidarReturns | None:
    """Every return of ``mav0/lidar0``, or None when the dataset has no LIDAR.

    Lines with a negative or fractional scan number or a range that is not positive are skipped
    and counted (``skipped``), with one warning, like any malformed line.
    """
    root = Path(root)
    if not (root / LIDAR_CSV).is_file():
        return None
    spec, scenario = read_lidar_spec(root)
    data = read_numeric_csv(root / LIDAR_CSV, 3, header=LIDAR_HEADER)  # clean files through numpy's parser
    scan, angle, rng = data.values.T
    keep = (scan >= 0) & (scan == np.floor(scan)) & (rng > 0.0)
    if not np.all(keep):
        first = int(np.flatnonzero(~keep)[0])
        log.warning("%s: skipped %d return(s) with a negative or fractional scan number or a range <= 0; "
                    "first at t_ns=%d", root / LIDAR_CSV, int(np.sum(~keep)), data.t_ns[first])
    if not np.any(keep):
        raise ValueError(f"{root / LIDAR_CSV}: no valid returns")
    return LidarReturns(spec, data.t_ns[keep], scan[keep], angle[keep], rng[keep], scenario,
                        skipped=data.skipped + int(np.sum(~keep)))


def lidar_summary(root: str | Path) -> dict | None:
    """What a replay says about the LIDAR it passes by, without parsing the lines: the scanner and how many returns."""
    root = Path(root)
    path = root / LIDAR_CSV
    if not path.is_file():
        return None
    spec, _ = read_lidar_spec(root)
    raw = path.read_bytes()
    comments = sum(1 for ln in raw[:4096].splitlines() if ln.startswith(b"#"))
    lines = raw.count(b"\n") + (0 if raw.endswith(b"\n") or not raw else 1) - comments
    return {"stream": LIDAR_CSV, "model": spec.model, "lines": lines}
