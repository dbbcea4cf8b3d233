"""Datasets on disk (extended ASL/EuRoC layout, docs/configuration.md "Datasets"): read and write.

What ``replay`` reads and ``simulate``/``import``/recording write, so every flight, simulated or
real, goes through the same files. Readers return whole-file numpy series in SI units; the IMU
comes out in body FRD (or raw sensor axes on request), GPS in local NED. Writers use fixed
number formats, so the same data always gives the same bytes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np
import pymap3d
import yaml

from vtolpose.drivers.files.calibration_yaml import DATASET_FORMAT, CalibrationError, calibration_from_yaml, calibration_to_yaml, load_yaml_file
from vtolpose.drivers.files.clock_steps import ClockStep, reanchor
from vtolpose.drivers.files.csvio import CsvData, in_time_order, read_numeric_csv, write_numeric_csv
from vtolpose.drivers.files.frames_csv import MAX_FRAME_PIXELS, load_grey, read_frame_index, write_frame_index, write_png
from vtolpose.drivers.files.lidar import LIDAR_CSV, LidarReturns, read_lidar, write_lidar
from vtolpose.drivers.files.series import GpsSeries, ImuSeries, TruthSeries
from vtolpose.estimator.core.calibration import Calibration

__all__ = [
    "CalibrationError", "Dataset", "DatasetWriter", "GpsSeries", "ImuSeries", "TruthSeries",
    "calibration_from_yaml", "calibration_to_yaml",
]

log = logging.getLogger(__name__)

IMU_CSV = "mav0/imu0/data.csv"
GPS_CSV = "mav0/gps0/data.csv"
GPS_SENSOR = "mav0/gps0/sensor.yaml"
GT_CSV = "mav0/state_groundtruth_estimate0/data.csv"
LEICA_CSV = "mav0/leica0/data.csv"
CAM_CSV = "mav0/cam0/data.csv"
CAM_DIR = "mav0/cam0/data"

IMU_HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
              "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")
GPS_HEADER_WGS84 = "#timestamp [ns],lat [deg],lon [deg],alt [m],sigma_h [m],sigma_v [m]"
GPS_HEADER_NED = "#timestamp [ns],p_x [m],p_y [m],p_z [m],sigma_h [m],sigma_v [m]"
GT_HEADER = ("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
             "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
             "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]")
LEICA_HEADER = "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m]"
GPS_FRAMES = ("WGS84", "NED")
SENSOR_FILES = {IMU_CSV: 6, GPS_CSV: 5}  # the streams whose clocks are checked against each other (columns)
MAX_GPS_HEIGHT_M = 1.0e5  # a WGS84 fix beyond ±100 km is a corrupt row (it would also make a useless origin)


@dataclass
class Dataset:
    """An opened dataset folder: its calibration, and readers for each sensor file."""

    root: Path
    calibration: Calibration
    meta: dict
    skipped: dict[str, int] = field(default_factory=dict)
    clock_steps: dict[str, list[ClockStep]] = field(default_factory=dict)  # per sensor file: steps undone
    # Each file is parsed (and its damage counted and warned about) once, however often it is asked
    # for: a replay, its report and its progress display all read the same series. Shared: read-only.
    _parsed: dict[str, object] = field(default_factory=dict, repr=False)

    @classmethod
    def open(cls, root: str | Path) -> "Dataset":
        root = Path(root)
        path = root / "dataset.yaml"
        if not root.is_dir():
            raise FileNotFoundError(f"{root}: dataset folder not found")
        if not path.is_file():
            raise FileNotFoundError(f"{path}: not found (every dataset needs its dataset.yaml)")
        doc = load_yaml_file(path)
        if not isinstance(doc, dict) or doc.get("format") != DATASET_FORMAT:
            got = doc.get("format") if isinstance(doc, dict) else doc
            raise CalibrationError(f"{path}: format: expected {DATASET_FORMAT!r}, got {got!r}")
        dataset = cls(root, calibration_from_yaml(doc, str(path)),
                      {"name": str(doc.get("name") or root.name), "description": str(doc.get("description") or "")})
        if (root / CAM_CSV).is_file() and dataset.calibration.camera is None:
            log.warning("%s: has %s but dataset.yaml has no camera calibration; images are ignored", root, CAM_CSV)
        return dataset

    @property
    def has_camera(self) -> bool:
        return self.calibration.camera is not None and (self.root / CAM_CSV).is_file()

    def _read(self, rel: str, n_values: int, header: str) -> tuple[np.ndarray, np.ndarray]:
        if rel not in self._parsed:
            if rel in SENSOR_FILES:
                t, values, skipped = self._anchored(rel, self._raw(rel, n_values, header))
            else:
                data = read_numeric_csv(self.root / rel, n_values, header=header)
                t, values, skipped = data.t_ns, data.values, data.skipped
            self.skipped[rel] = skipped
            if len(t) == 0:
                raise ValueError(f"{self.root / rel}: no valid data lines")
            self._parsed[rel] = (t, values)
        return self._parsed[rel]

    def _raw(self, rel: str, n_values: int = 0, header: str = "") -> CsvData:
        """A sensor file's rows that parse, in file order (kept until its own clock steps are undone)."""
        key = f"{rel} raw"
        if key not in self._parsed:
            n_values = n_values or SENSOR_FILES[rel]
            self._parsed[key] = read_numeric_csv(self.root / rel, n_values, header=header, in_order=False)
        return self._parsed[key]

    def _end(self, rel: str) -> int | None:
        """The last stamp of another sensor file (its steps undone if it was read already); None: no such file,
        or one that cannot be read (the error is its own replay's to raise)."""
        if f"{rel} end" in self._parsed:
            return self._parsed[f"{rel} end"]
        if not (self.root / rel).is_file():
            return None
        try:
            if rel == CAM_CSV:
                frames, _ = read_frame_index(self.root / CAM_CSV, self.root / CAM_DIR, in_order=False)
                self._parsed[f"{rel} end"] = robust_end(np.array([t for t, _ in frames], dtype=np.int64))
                return self._parsed[f"{rel} end"]
            t = self._raw(rel).t_ns
        except (OSError, ValueError):
            return None
        return robust_end(t)

    def _anchored(self, rel: str, data: CsvData) -> tuple[np.ndarray, np.ndarray, int]:
        """``data`` with its clock steps undone against the other sensor files' end (clock_steps.py), then
        the rows still out of order dropped and counted."""
        ends = [end for end in (self._end(other) for other in (*SENSOR_FILES, CAM_CSV) if other != rel) if end is not None]
        t, steps = reanchor(data.t_ns, max(ends) if ends else None)
        self._parsed.pop(f"{rel} raw", None)
        self._parsed[f"{rel} end"] = robust_end(t)
        if steps:
            self.clock_steps[rel] = steps
            for step in steps:
                log.warning("%s: %s", self.root / rel, step.describe())
        keep = in_time_order(t)
        dropped = int(np.count_nonzero(~keep))
        if dropped:
            first = int(np.flatnonzero(~keep)[0])
            log.warning("%s: skipped %d line(s) with a time not after the previous line; first at row %d (t_ns=%d)",
                        self.root / rel, dropped, first + 1, int(data.t_ns[first]))
            return t[keep], data.values[keep], data.skipped + dropped
        return t, data.values, data.skipped

    def camera_frames(self) -> list[tuple[int, Path]]:
        """``(t_ns, image path)`` of every frame in ``cam0/data.csv``, in time order (bad lines counted; clock
        steps undone against the IMU and GPS files, as theirs against each other and the camera's)."""
        if not (self.root / CAM_CSV).is_file():
            return []
        frames, skipped = read_frame_index(self.root / CAM_CSV, self.root / CAM_DIR, in_order=False)
        t, values, skipped = self._anchored(CAM_CSV, CsvData(np.array([t for t, _ in frames], dtype=np.int64),
                                                             np.arange(len(frames)).reshape(-1, 1), skipped))
        self.skipped[CAM_CSV] = skipped
        return [(int(t_ns), frames[int(k)][1]) for t_ns, k in zip(t.tolist(), values[:, 0].tolist())]

    def load_frame(self, path: Path) -> np.ndarray | None:
        """A frame as a grey uint8 array; a missing or unreadable file is a counted skip (None)."""
        cam = self.calibration.camera
        # A frame may be somewhat off its calibrated size (refused later as the wrong size), never huge.
        image = load_grey(path, MAX_FRAME_PIXELS if cam is None else min(MAX_FRAME_PIXELS, 4 * cam.width * cam.height))
        if image is None:
            self.skipped[CAM_DIR] = self.skipped.get(CAM_DIR, 0) + 1
        return image

    def imu_raw(self) -> ImuSeries:
        """IMU samples in the sensor's own axes, as recorded (the same arrays on every call: not to be changed)."""
        series = self._parsed.get("imu series")
        if series is None:
            t, v = self._read(IMU_CSV, 6, IMU_HEADER)
            # Columns of their own (contiguous, as the compiled kernels take them); the table is not kept.
            series = self._parsed["imu series"] = ImuSeries(t, np.ascontiguousarray(v[:, :3]), np.ascontiguousarray(v[:, 3:]))
            del self._parsed[IMU_CSV]
        return series

    def imu(self, R_BI: np.ndarray | None = None) -> ImuSeries:
        """IMU samples rotated into body FRD with the dataset's ``R_BI`` (or the one given). An IMU mounted
        in body axes needs no rotation: its arrays are the recorded ones, not a copy (an hour at 200 Hz
        is 35 MB)."""
        raw = self.imu_raw()
        r = self.calibration.imu.R_BI if R_BI is None else np.asarray(R_BI, dtype=float)
        if np.array_equal(r, np.eye(3)):
            return raw
        return ImuSeries(raw.t_ns, raw.gyro @ r.T, raw.accel @ r.T)

    def gps(self) -> GpsSeries | None:
        """GPS fixes in local NED (geodetic files converted around the dataset origin or the first fix)."""
        if not (self.root / GPS_CSV).is_file():
            return None
        if "gps" not in self._parsed:
            self._parsed["gps"] = self._gps()
        return self._parsed["gps"]

    def _gps(self) -> GpsSeries:
        frame = _gps_frame(self.root / GPS_SENSOR)
        t, v = self._read(GPS_CSV, 5, GPS_HEADER_WGS84 if frame == "WGS84" else GPS_HEADER_NED)
        t, v = self._keep_fixes(t, v, np.all(v[:, 3:5] > 0.0, axis=1), "sigma <= 0")
        origin = self.calibration.gps.origin_lla
        if frame == "WGS84":
            on_earth = (np.abs(v[:, 0]) <= 90.0) & (np.abs(v[:, 1]) <= 180.0) & (np.abs(v[:, 2]) <= MAX_GPS_HEIGHT_M)
            t, v = self._keep_fixes(t, v, on_earth,
                                    f"lat beyond ±90°, lon beyond ±180° or |alt| > {MAX_GPS_HEIGHT_M:g} m")
            if origin is None:
                origin = (float(v[0, 0]), float(v[0, 1]), float(v[0, 2]))
            p = np.column_stack(pymap3d.geodetic2ned(v[:, 0], v[:, 1], v[:, 2], *origin))
        else:
            p = v[:, :3]
        return GpsSeries(t, p, v[:, 3], v[:, 4], origin)

    def _keep_fixes(self, t: np.ndarray, v: np.ndarray, keep: np.ndarray, why: str) -> tuple[np.ndarray, np.ndarray]:
        """The GPS rows where ``keep`` holds; the others are counted as skipped, with one warning."""
        if np.all(keep):
            return t, v
        first = int(np.flatnonzero(~keep)[0])
        log.warning("%s: skipped %d fix(es) with %s; first at t_ns=%d",
                    self.root / GPS_CSV, int(np.sum(~keep)), why, t[first])
        self.skipped[GPS_CSV] += int(np.sum(~keep))
        if not np.any(keep):
            raise ValueError(f"{self.root / GPS_CSV}: no usable fix (every one has {why})")
        return t[keep], v[keep]

    def truth(self) -> TruthSeries | None:
        """Full truth if the dataset has it, else position-only Leica-style truth, else None."""
        if (self.root / GT_CSV).is_file():
            t, v = self._read(GT_CSV, 16, GT_HEADER)
            norm = np.linalg.norm(v[:, 3:7], axis=1)
            if np.any(np.abs(norm - 1.0) > 1e-3):
                i = int(np.argmax(np.abs(norm - 1.0)))
                raise ValueError(
                    f"{self.root / GT_CSV}: quaternion of norm {norm[i]:.6f} at t_ns={t[i]} (expected unit)")
            return TruthSeries(t, v[:, :3], v[:, 3:7] / norm[:, None], v[:, 7:10], v[:, 10:13], v[:, 13:16])
        if (self.root / LEICA_CSV).is_file():
            t, v = self._read(LEICA_CSV, 3, LEICA_HEADER)
            return TruthSeries(t, v)
        return None

    def lidar(self) -> LidarReturns | None:
        """The LIDAR's returns and scanner (``mav0/lidar0``, not fused: for the mapper), or None."""
        returns = read_lidar(self.root)
        if returns is not None:
            self.skipped[LIDAR_CSV] = returns.skipped
        return returns


def robust_end(t_ns: np.ndarray, spare: int = 5) -> int | None:
    """A stream's last stamp, passing over a few corrupt ones beyond it (the ``spare``-th largest)."""
    if len(t_ns) == 0:
        return None
    return int(np.partition(t_ns, len(t_ns) - min(spare, len(t_ns)))[len(t_ns) - min(spare, len(t_ns))])


def _gps_frame(path: Path) -> str:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found (it says whether gps0/data.csv is WGS84 or local NED)")
    doc = load_yaml_file(path)
    frame = doc.get("frame") if isinstance(doc, dict) else None
    if frame not in GPS_FRAMES:
        raise CalibrationError(f"{path}: frame: expected one of {list(GPS_FRAMES)}, got {frame!r}")
    return frame


IMU_FORMATS = ["%.10f"] * 6
GPS_WGS84_FORMATS = ["%.10f", "%.10f", "%.6f", "%.6f", "%.6f"]  # lat, lon, alt, sigma_h, sigma_v
GPS_NED_FORMATS = ["%.6f"] * 5


def gps_sensor_yaml(frame: str) -> str:
    """``gps0/sensor.yaml``: whether ``gps0/data.csv`` holds WGS84 or local NED positions."""
    return f"# gps0/data.csv holds {'local NED positions' if frame == 'NED' else 'WGS84 lat/lon/alt'}\nframe: {frame}\n"


def dataset_yaml_text(calibration: Calibration, name: str, description: str) -> str:
    """The ``dataset.yaml`` document of a dataset with this calibration."""
    doc = {"format": DATASET_FORMAT, "name": name, "description": description, **calibration_to_yaml(calibration)}
    return yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120, allow_unicode=True)


def refuse_existing_dataset(out: str | Path, overwrite: bool) -> None:
    """FileExistsError when ``out`` already holds a dataset and replacing it was not asked for.

    Called before any work (simulating, rendering, importing), so a refusal costs nothing.
    """
    if (Path(out) / "dataset.yaml").exists() and not overwrite:
        raise FileExistsError(f"{out}: already holds a dataset (dataset.yaml); use --force to replace it")


def set_camera_time_offset(root: str | Path, offset_s: float, note: str) -> None:
    """Rewrite ``root``'s dataset.yaml with ``camera.time_offset_s = offset_s`` (added to every frame stamp to put
    it on the IMU clock), ``note`` appended to its description so the file says where the number came from."""
    dataset = Dataset.open(root)
    camera = dataset.calibration.camera
    if camera is None:
        raise ValueError(f"{root}: dataset.yaml has no camera to give a time offset")
    camera.time_offset_s = float(offset_s)
    description = "; ".join(x for x in (dataset.meta["description"], note) if x)
    DatasetWriter(root).write_calibration(dataset.calibration, dataset.meta["name"], description)


class DatasetWriter:
    """Writes the files of one dataset folder (created if needed)."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

    def write_calibration(self, calibration: Calibration, name: str, description: str) -> None:
        (self.root / "dataset.yaml").write_text(dataset_yaml_text(calibration, name, description), encoding="utf-8",
                                                newline="\n")

    def write_imu(self, imu: ImuSeries) -> None:
        """IMU samples in sensor axes (``dataset.yaml``'s R_BI maps them to body)."""
        write_numeric_csv(self.root / IMU_CSV, IMU_HEADER, imu.t_ns, np.hstack([imu.gyro, imu.accel]), IMU_FORMATS)

    def write_gps(self, gps: GpsSeries, geodetic_origin: tuple[float, float, float] | None = None) -> None:
        """Fixes as local NED, or as WGS84 lat/lon/alt around ``geodetic_origin``.

        A WGS84 file is read back around the calibration's ``gps.origin`` (or the first fix if
        that is null), so pass the same origin to the calibration to get the same NED back.
        """
        sigmas = np.column_stack([gps.sigma_h, gps.sigma_v])
        if geodetic_origin is None:
            frame, header, formats, pos = "NED", GPS_HEADER_NED, GPS_NED_FORMATS, gps.p_ned
        else:
            lat, lon, alt = pymap3d.ned2geodetic(*gps.p_ned.T, *geodetic_origin)
            frame, header, formats = "WGS84", GPS_HEADER_WGS84, GPS_WGS84_FORMATS
            pos = np.column_stack([lat, lon, alt])
        write_numeric_csv(self.root / GPS_CSV, header, gps.t_ns, np.hstack([pos, sigmas]), formats)
        (self.root / GPS_SENSOR).write_text(gps_sensor_yaml(frame), encoding="utf-8", newline="\n")

    def write_camera_frames(self, frames: Iterable[tuple[int, np.ndarray]]) -> int:
        """Images as ``cam0/data/<t_ns>.png`` plus their index; returns how many were written."""
        folder = self.root / CAM_DIR
        folder.mkdir(parents=True, exist_ok=True)
        times = []
        for t_ns, image in frames:
            write_png(folder / f"{int(t_ns)}.png", image)
            times.append(int(t_ns))
        write_frame_index(self.root / CAM_CSV, times)
        return len(times)

    def write_truth(
        self, truth: TruthSeries, biases_g: np.ndarray | None = None, biases_a: np.ndarray | None = None
    ) -> None:
        """Full 17-column truth when it has attitude, else position-only ``leica0``.

        Full truth needs velocity; biases default to the series' own, then to zero.
        """
        if truth.q is None:
            write_numeric_csv(self.root / LEICA_CSV, LEICA_HEADER, truth.t_ns, truth.p, ["%.9f"] * 3)
            return
        if truth.v is None:
            raise ValueError("write_truth: full truth (with q) needs v; give v or drop q for position-only truth")
        n = len(truth.t_ns)
        bg = next(b for b in (biases_g, truth.bias_g, np.zeros((n, 3))) if b is not None)
        ba = next(b for b in (biases_a, truth.bias_a, np.zeros((n, 3))) if b is not None)
        bg, ba = np.broadcast_to(bg, (n, 3)), np.broadcast_to(ba, (n, 3))
        values = np.hstack([truth.p, truth.q, truth.v, bg, ba])
        formats = ["%.9f"] * 3 + ["%.12f"] * 4 + ["%.9f"] * 9
        write_numeric_csv(self.root / GT_CSV, GT_HEADER, truth.t_ns, values, formats)

    def write_lidar(self, returns: LidarReturns) -> None:
        """Every return as ``lidar0/data.csv`` and the scanner with its mounting as ``lidar0/sensor.yaml``."""
        write_lidar(self.root, returns)
