"""Import an ASL/EuRoC MAV folder (IMU, truth, camera) into a vtolpose dataset, optionally with a GPS.

This is how the thesis' "Test 1: IMU + GPS" is replayed on real data: the real IMU, the
flight's truth (``euroc_truth``: EuRoC's ground-truth estimate, the Leica or Vicon track, or a
TUM file) at full rate, and a GPS made the way the thesis made it (truth subsampled to GPS rate
plus Gaussian noise, σ_z² = 2 σ_xy²). ``cam0`` comes along (``euroc_camera``) so the images
replay through the visual pipeline. The sensor mounting and the tracker frame come from a
small YAML file (``config/euroc_vi_sensor.yaml`` by default, the same for every EuRoC flight),
not from code.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from vtolpose.drivers.files.calibration_yaml import YamlReader, load_yaml_file
from vtolpose.drivers.files.csvio import NS_PER_S, read_numeric_csv
from vtolpose.drivers.files.dataset import (
    CAM_CSV, CAM_DIR, GPS_CSV, GPS_SENSOR, GT_CSV, IMU_HEADER, LEICA_CSV, DatasetWriter, GpsSeries, ImuSeries,
    TruthSeries,
)
from vtolpose.drivers.files.euroc_camera import camera_calibration, copy_frames
from vtolpose.drivers.files.euroc_truth import EurocTruth, Frames, read_mount, read_truth
from vtolpose.drivers.simulator.gps_model import GpsErrorModel, gps_errors
from vtolpose.estimator.core.calibration import Calibration, GpsCalibration, ImuCalibration, ImuNoise
from vtolpose.estimator.metrics import gps_error_rmse

DEFAULT_MOUNTING_NAME = "euroc_vi_sensor.yaml"
TRUTH_FOLDERS = ("state_groundtruth_estimate0", "leica0", "vicon0")
_EUROC_NOISE_KEYS = ("gyroscope_noise_density", "gyroscope_random_walk",
                     "accelerometer_noise_density", "accelerometer_random_walk")


def default_mounting_path() -> Path:
    """``euroc_vi_sensor.yaml``, shipped in the ``vtolpose.config`` package."""
    return Path(str(resources.files("vtolpose.config") / DEFAULT_MOUNTING_NAME))


def _load_yaml(path: Path) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found")
    doc = load_yaml_file(path)
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: expected a mapping at the top level, got {doc!r}")
    return doc


@dataclass(frozen=True)
class EurocSetup:
    """What the importer must be told about the EuRoC vehicle (``config/euroc_vi_sensor.yaml``)."""

    R_BI: np.ndarray  # IMU axes -> body FRD
    R_WL: np.ndarray  # tracker frame -> world NED
    leica_time_offset_s: float  # added to Leica stamps to put them on the IMU clock
    in_flight_noise: ImuNoise | None  # replaces imu0/sensor.yaml's static densities when given


def load_mounting(path: str | Path) -> EurocSetup:
    """The importer's configuration file, validated; errors name the file and the key."""
    path = Path(path)
    doc = _load_yaml(path)
    y = YamlReader(str(path))
    y.mapping(doc, "(top level)", {"R_BI", "R_WL", "leica_time_offset_s", "in_flight_noise"}, required=("R_BI", "R_WL"))
    offset = y.number(doc.get("leica_time_offset_s", 0.0), "leica_time_offset_s")
    if abs(offset) > 5.0:
        raise y.fail("leica_time_offset_s", "an offset of at most 5 s", offset)
    noise = None
    if doc.get("in_flight_noise") is not None:
        block = y.mapping(doc["in_flight_noise"], "in_flight_noise", set(_EUROC_NOISE_KEYS), required=_EUROC_NOISE_KEYS)
        noise = ImuNoise.isotropic(*(y.number(block[k], f"in_flight_noise.{k}", non_negative=True) for k in _EUROC_NOISE_KEYS))
    return EurocSetup(y.rotation(doc["R_BI"], "R_BI"), y.rotation(doc["R_WL"], "R_WL"), offset, noise)


def _imu_calibration(path: Path, R_BI: np.ndarray) -> ImuCalibration:
    doc = _load_yaml(path)
    y = YamlReader(str(path))
    for key in ("rate_hz", *_EUROC_NOISE_KEYS):
        if key not in doc:
            raise ValueError(f"{path}: {key}: missing (required)")
    noise = ImuNoise.isotropic(*(y.number(doc[k], k, non_negative=True) for k in _EUROC_NOISE_KEYS))
    return ImuCalibration(rate_hz=y.number(doc["rate_hz"], "rate_hz", positive=True), noise=noise, R_BI=R_BI)


def subsample(t_ns: np.ndarray, rate_hz: float) -> np.ndarray:
    """Indices of the samples nearest a ``rate_hz`` clock started at the first sample.

    A tick with no sample within half a period (a gap in the track) gets none. Plain
    "at least 1/rate apart" would give ~7 Hz from the jittery ~20 Hz Leica track.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    period = round(NS_PER_S / rate_hz)
    ticks = t_ns[0] + period * np.arange((t_ns[-1] - t_ns[0]) // period + 1, dtype=np.int64)
    right = np.clip(np.searchsorted(t_ns, ticks), 1, t_ns.size - 1)
    nearest = np.where(ticks - t_ns[right - 1] <= t_ns[right] - ticks, right - 1, right)
    close = 2 * np.abs(t_ns[nearest] - ticks) < period
    return np.unique(nearest[close])


def simulated_gps(truth: TruthSeries, rate_hz: float, sigma_m: float, seed: int) -> GpsSeries:
    """The thesis' GPS: truth positions at ``rate_hz`` plus N(0, σ²) per horizontal axis, N(0, 2σ²) vertically."""
    if rate_hz <= 0.0 or sigma_m <= 0.0:
        raise ValueError(f"gps rate ({rate_hz} Hz) and sigma ({sigma_m} m) must be positive")
    idx = subsample(truth.t_ns, rate_hz)
    model = GpsErrorModel(sigma_m, rate_hz)
    noise = gps_errors(truth.t_ns[idx] * 1e-9, model, np.random.default_rng(seed))
    return GpsSeries(truth.t_ns[idx], truth.p[idx] + noise, model.sigma_h, model.sigma_v)


def within(gps: GpsSeries, imu_t_ns: np.ndarray) -> GpsSeries:
    """The fixes inside the IMU recording: a receiver is not heard before the vehicle's IMU starts or after it
    stops (the truth often runs on for a second or two, and a fix there would look like a dead IMU)."""
    keep = (gps.t_ns >= imu_t_ns[0]) & (gps.t_ns <= imu_t_ns[-1])
    return GpsSeries(gps.t_ns[keep], gps.p_ned[keep], gps.sigma_h[keep], gps.sigma_v[keep], gps.origin_lla)


def _optional_truth(mav: Path, frames: Frames, leica_offset_s: float, truth_file: Path | None) -> EurocTruth | None:
    """The flight's truth, or None when the recording has none (a user's own flight); a truth that is
    there but broken, or a ``--truth`` file that is missing, is still an error."""
    if truth_file is None and not any((mav / name / "data.csv").is_file() for name in TRUTH_FOLDERS):
        return None
    return read_truth(mav, frames, leica_offset_s, truth_file)


def import_euroc(
    src: str | Path,
    out: str | Path,
    gps_rate_hz: float | None = None,
    gps_sigma_m: float = 0.02,
    seed: int = 0,
    mounting: str | Path | None = None,
    overwrite: bool = False,
    truth_file: str | Path | None = None,
    camera: bool = True,
) -> dict[str, Any]:
    """Convert EuRoC ``src`` (``mav0/imu0``, a truth, optionally ``mav0/cam0``) into dataset ``out``; returns a summary.

    Malformed CSV lines are skipped and counted (see the summary). The IMU stays in sensor axes
    with ``R_BI`` from ``mounting``. The truth is ``truth_file`` (TUM or EuRoC CSV: the IMU's
    pose, on the IMU clock) or the first of ``state_groundtruth_estimate0``, ``leica0``,
    ``vicon0`` (``vtolpose.drivers.files.euroc_truth``), in NED and body FRD, tracking the point
    ``truth.point_b``. With ``gps_rate_hz`` a GPS is made from it (seeded: same seed, same
    bytes) with that point as antenna. ``cam0``, when present and ``camera``, comes along with
    its calibration. Refuses to replace an existing dataset unless ``overwrite``.
    """
    src, out = Path(src), Path(out)
    mounting_path = Path(mounting) if mounting is not None else default_mounting_path()
    if (out / "dataset.yaml").exists() and not overwrite:
        raise FileExistsError(f"{out}: already holds a dataset (dataset.yaml); pass overwrite to replace it")
    setup = load_mounting(mounting_path)
    mav = src / "mav0"
    imu_cal = _imu_calibration(mav / "imu0" / "sensor.yaml", setup.R_BI)
    if setup.in_flight_noise is not None:
        imu_cal.noise = setup.in_flight_noise
    imu = read_numeric_csv(mav / "imu0" / "data.csv", 6, header=IMU_HEADER)
    if imu.t_ns.size < 2:
        raise ValueError(f"{mav / 'imu0' / 'data.csv'}: fewer than 2 valid samples")
    frames = Frames(setup.R_BI, setup.R_WL, read_mount(mav / "imu0" / "sensor.yaml"))
    found = _optional_truth(mav, frames, setup.leica_time_offset_s, Path(truth_file) if truth_file is not None else None)
    truth = found.series if found is not None else None
    point_b = found.point_b if found is not None else np.zeros(3)
    if gps_rate_hz is not None and truth is None:
        raise ValueError(f"{mav}: --gps-rate makes the GPS from the truth, and this recording has none "
                         "(state_groundtruth_estimate0, leica0, vicon0); give one with --truth, or import without --gps-rate")
    gps = None if gps_rate_hz is None else within(simulated_gps(truth, gps_rate_hz, gps_sigma_m, seed), imu.t_ns)
    cam_dir = mav / "cam0"
    use_camera = camera and (cam_dir / "data.csv").is_file() and (cam_dir / "sensor.yaml").is_file()

    calibration = Calibration(
        imu=imu_cal,
        gps=GpsCalibration(lever_arm_b=point_b if gps is not None else np.zeros(3)),
        camera=camera_calibration(cam_dir / "sensor.yaml", frames) if use_camera else None,
        truth_point_b=point_b,
    )
    gps_text = (f"GPS = truth track subsampled to {gps_rate_hz:g} Hz + Gaussian noise sigma_xy={gps_sigma_m:g} m, "
                f"sigma_z=sqrt(2) sigma_xy, seed {seed}, kept within the IMU recording" if gps is not None else "no GPS")
    if found is None:
        truth_text = "no truth (the recording has none: a replay reports no scores)"
    else:
        shift = f" shifted by {found.time_offset_s * 1e3:+.0f} ms onto the IMU clock" if found.time_offset_s else ""
        truth_text = (f"truth from {found.path.name if found.source == 'file' else found.source}{shift} "
                      f"({'pose' if truth.q is not None else 'position'}, NED)")
    description = (f"EuRoC {src.name} imported by vtolpose (vtolpose.drivers.files.euroc_import): real IMU in sensor axes, "
                   f"{truth_text}, mounting from {mounting_path.name}; IMU noise "
                   f"{'in flight, from ' + mounting_path.name if setup.in_flight_noise is not None else 'from imu0/sensor.yaml'}; "
                   f"{gps_text}{'; cam0 images' if use_camera else ''}")
    writer = DatasetWriter(out)
    for stale in (GPS_CSV, GPS_SENSOR, GT_CSV, LEICA_CSV, CAM_CSV):
        (out / stale).unlink(missing_ok=True)
    if (out / CAM_DIR).is_dir() and not use_camera:
        shutil.rmtree(out / CAM_DIR)
    name = src.name if "euroc" in src.name.lower() else f"euroc-{src.name}"
    writer.write_calibration(calibration, name, description)
    writer.write_imu(ImuSeries(imu.t_ns, imu.values[:, :3], imu.values[:, 3:]))
    if truth is not None:
        writer.write_truth(truth)
    if gps is not None:
        writer.write_gps(gps)

    summary: dict[str, Any] = {
        "out": str(out),
        "imu_samples": int(imu.t_ns.size),
        "imu_lines_skipped": imu.skipped,
        "imu_rate_hz_measured": float(NS_PER_S / np.median(np.diff(imu.t_ns))),
        "truth_source": found.source if found is not None else "none",
        "duration_s": float((imu.t_ns[-1] - imu.t_ns[0]) * 1e-9),
        "gps_fixes": 0,
        "camera_frames": 0,
    }
    if found is not None:
        summary.update(truth_file=str(found.path), truth_samples=int(truth.t_ns.size), truth_lines_skipped=found.skipped,
                       truth_has_attitude=truth.q is not None, truth_time_offset_s=found.time_offset_s,
                       truth_point_b=point_b.tolist())
    if use_camera:
        summary["camera_frames"], summary["camera_frames_skipped"] = copy_frames(cam_dir, out)
    if gps is not None:
        summary["gps_fixes"] = int(gps.t_ns.size)
        summary["gps_rate_hz_measured"] = float(NS_PER_S / np.median(np.diff(gps.t_ns)))
        summary["gps_error_vs_truth"] = gps_error_rmse(gps, truth, point_b, point_b)
    return summary
