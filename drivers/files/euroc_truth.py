"""The truth of an EuRoC flight, from whichever source it comes with, in our frames.

EuRoC flights carry their reference in one of several forms: ``state_groundtruth_estimate0``
(the dataset authors' fusion of motion capture and IMU: the IMU's pose, velocity and biases,
17 columns), the raw ``leica0`` prism track (position only) or the raw ``vicon0`` marker pose;
tools often export the first as TUM. Each source S has its pose in the tracker frame R and,
in its ``sensor.yaml``, its mounting ``T_BS`` on EuRoC's body B; the IMU has its own ``T_BS``.
Our body is FRD at the IMU (``R_BI`` maps IMU axes to it), our world NED (``R_WL`` maps the
tracker frame to it), so

    R_NED←FRD = R_WL · R_R←S · R_BSᵀ · R_BI_euroc · R_BIᵀ          (R_BI_euroc: IMU → B)
    point_b   = R_BI · R_BI_eurocᵀ · (t_BS − t_BI_euroc)             (the tracked point, body FRD)

and the tracked point's position is ``R_WL p_R``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vtolpose.drivers.files.calibration_yaml import YamlReader, load_yaml_file
from vtolpose.drivers.files.csvio import NS_PER_S, read_numeric_csv
from vtolpose.drivers.files.dataset import GT_HEADER, LEICA_HEADER, TruthSeries
from vtolpose.drivers.files.tum import read_tum
from vtolpose.estimator.core.rotation import quat_to_rot, rot_to_quat

VICON_HEADER = "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"
TRUTH_SOURCES = ("file", "state_groundtruth_estimate0", "leica0", "vicon0")


@dataclass(frozen=True)
class Mount:
    """A EuRoC sensor's pose on EuRoC's body frame B (its ``sensor.yaml`` ``T_BS``)."""

    R_BS: np.ndarray
    t_BS: np.ndarray

    @classmethod
    def identity(cls) -> "Mount":
        return cls(np.eye(3), np.zeros(3))


def read_mount(path: Path) -> Mount:
    """``T_BS`` of a EuRoC ``sensor.yaml``; errors name the file and the key."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found")
    doc = load_yaml_file(path)
    y = YamlReader(str(path))
    if not isinstance(doc, dict):
        raise y.fail("(top level)", "a mapping", doc)
    t_bs = doc.get("T_BS")
    if not isinstance(t_bs, dict):
        raise y.fail("T_BS", "a mapping with data: [16 numbers]", t_bs)
    m = y.vector(t_bs.get("data"), "T_BS.data", 16).reshape(4, 4)
    rotation = m[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4) or np.linalg.det(rotation) < 0.0:
        raise y.fail("T_BS.data", "a rigid transform (its 3 x 3 block a rotation)", m.tolist())
    u, _, vt = np.linalg.svd(rotation)  # the printed digits are not exactly orthonormal
    return Mount(u @ vt, m[:3, 3])


@dataclass(frozen=True)
class Frames:
    """What maps EuRoC's axes into ours: IMU → FRD, tracker → NED, and the IMU's own mounting on B."""

    R_BI: np.ndarray
    R_WL: np.ndarray
    imu: Mount

    def body_rotation(self, source: Mount) -> np.ndarray:
        """``M`` with ``R_NED←FRD = R_WL · R_R←S · M``."""
        return source.R_BS.T @ self.imu.R_BS @ self.R_BI.T

    def point_b(self, source: Mount) -> np.ndarray:
        """The source's origin (the point its positions track) in body FRD."""
        return self.R_BI @ self.imu.R_BS.T @ (source.t_BS - self.imu.t_BS)


@dataclass(frozen=True)
class EurocTruth:
    series: TruthSeries  # NED positions of point_b; attitude body FRD → NED when the source has it
    point_b: np.ndarray
    source: str  # one of TRUTH_SOURCES
    path: Path
    time_offset_s: float  # added to the source's stamps
    skipped: int = 0  # malformed lines of the source file, skipped and counted


def _pose_truth(t_ns: np.ndarray, p_r: np.ndarray, q_r: np.ndarray, frames: Frames, mount: Mount,
                v_r: np.ndarray | None = None) -> TruthSeries:
    R = frames.R_WL @ quat_to_rot(q_r) @ frames.body_rotation(mount)
    p = p_r @ frames.R_WL.T
    if v_r is not None:
        v = v_r @ frames.R_WL.T
    else:  # motion-capture poses carry no velocity: central differences of the positions
        v = np.gradient(p, t_ns.astype(float) * 1e-9, axis=0) if len(t_ns) > 1 else np.zeros_like(p)
    return TruthSeries(t_ns, p, rot_to_quat(R), v)


def read_truth(mav: Path, frames: Frames, leica_offset_s: float, truth_file: Path | None = None) -> EurocTruth:
    """The flight's truth: ``truth_file`` (TUM or EuRoC CSV, the IMU's pose on the IMU clock) when given,
    else the first of ``state_groundtruth_estimate0``, ``leica0`` (stamps shifted by ``leica_offset_s``),
    ``vicon0`` found under ``mav``."""
    if truth_file is not None:
        t_ns, p, q = read_tum(truth_file)
        if t_ns.size < 2:
            raise ValueError(f"{truth_file}: fewer than 2 poses")
        imu_mount = frames.imu
        if q is None:
            return EurocTruth(TruthSeries(t_ns, p @ frames.R_WL.T), np.zeros(3), "file", truth_file, 0.0)
        return EurocTruth(_pose_truth(t_ns, p, q, frames, imu_mount), np.zeros(3), "file", truth_file, 0.0)
    gt = mav / "state_groundtruth_estimate0"
    if (gt / "data.csv").is_file():
        data = _read(gt / "data.csv", 16, GT_HEADER)
        mount = read_mount(gt / "sensor.yaml") if (gt / "sensor.yaml").is_file() else Mount.identity()
        v = data.values
        series = _pose_truth(data.t_ns, v[:, 0:3], v[:, 3:7], frames, mount, v[:, 7:10])
        # Biases are in the source's axes (the IMU's, for EuRoC's estimate): into body FRD.
        to_body = frames.R_BI @ frames.imu.R_BS.T @ mount.R_BS
        series.bias_g, series.bias_a = v[:, 10:13] @ to_body.T, v[:, 13:16] @ to_body.T
        return EurocTruth(series, frames.point_b(mount), "state_groundtruth_estimate0", gt / "data.csv", 0.0,
                          data.skipped)
    leica = mav / "leica0"
    if (leica / "data.csv").is_file():
        data = _read(leica / "data.csv", 3, LEICA_HEADER)
        mount = read_mount(leica / "sensor.yaml")
        t_ns = data.t_ns + int(round(leica_offset_s * NS_PER_S))
        return EurocTruth(TruthSeries(t_ns, data.values @ frames.R_WL.T), frames.point_b(mount), "leica0",
                          leica / "data.csv", leica_offset_s, data.skipped)
    vicon = mav / "vicon0"
    if (vicon / "data.csv").is_file():
        data = _read(vicon / "data.csv", 7, VICON_HEADER)
        mount = read_mount(vicon / "sensor.yaml")
        series = _pose_truth(data.t_ns, data.values[:, 0:3], _unit(data.values[:, 3:7], vicon / "data.csv"), frames, mount)
        return EurocTruth(series, frames.point_b(mount), "vicon0", vicon / "data.csv", 0.0, data.skipped)
    raise FileNotFoundError(
        f"{mav}: no truth found (looked for state_groundtruth_estimate0/data.csv, leica0/data.csv, vicon0/data.csv); "
        "give a TUM file with --truth")


def _read(path: Path, n_values: int, header: str):
    data = read_numeric_csv(path, n_values, header=header)
    if data.t_ns.size < 2:
        raise ValueError(f"{path}: fewer than 2 valid samples")
    return data


def _unit(q: np.ndarray, path: Path) -> np.ndarray:
    norm = np.linalg.norm(q, axis=1)
    if np.any(np.abs(norm - 1.0) > 1e-3):
        i = int(np.argmax(np.abs(norm - 1.0)))
        raise ValueError(f"{path}: quaternion of norm {norm[i]:.6f} on data line {i + 1} (expected unit)")
    return q / norm[:, None]
