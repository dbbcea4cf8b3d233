"""Calibration and noise of the sensor set: what a dataset's ``dataset.yaml`` holds.

Pure data with validation; reading and writing YAML is the drivers' job
(``vtolpose.drivers.files.dataset``). Frames: ``R_BI`` maps IMU sensor axes to body FRD; lever arms are in
body FRD, metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from vtolpose.estimator.core.rotation import is_proper_rotation

STANDARD_GRAVITY = 9.80665


@dataclass(slots=True)
class ImuNoise:
    """Continuous-time densities: white noise and bias random walk, per axis (3-vectors).

    Units: gyro noise rad/s/√Hz, gyro random walk rad/s²/√Hz, accel noise m/s²/√Hz,
    accel random walk m/s³/√Hz — the Kalibr/EuRoC convention.
    """

    gyro_noise_density: np.ndarray
    gyro_random_walk: np.ndarray
    accel_noise_density: np.ndarray
    accel_random_walk: np.ndarray

    @classmethod
    def isotropic(cls, gyro_nd: float, gyro_rw: float, accel_nd: float, accel_rw: float) -> "ImuNoise":
        return cls(*(np.full(3, float(x)) for x in (gyro_nd, gyro_rw, accel_nd, accel_rw)))

    def __post_init__(self) -> None:
        for name in ("gyro_noise_density", "gyro_random_walk", "accel_noise_density", "accel_random_walk"):
            value = np.broadcast_to(np.asarray(getattr(self, name), dtype=float), (3,)).copy()
            if not np.all(np.isfinite(value)) or np.any(value < 0.0):
                raise ValueError(f"imu noise {name} must be finite and non-negative, got {value.tolist()}")
            setattr(self, name, value)


@dataclass(slots=True)
class ImuCalibration:
    rate_hz: float
    noise: ImuNoise
    R_BI: np.ndarray = field(default_factory=lambda: np.eye(3))
    gravity: float = STANDARD_GRAVITY

    def __post_init__(self) -> None:
        self.R_BI = np.asarray(self.R_BI, dtype=float).reshape(3, 3)
        if not is_proper_rotation(self.R_BI):
            raise ValueError("imu R_BI must be a proper rotation matrix (orthonormal, det +1)")


@dataclass(slots=True)
class GpsCalibration:
    """Antenna lever arm in body FRD, the geodetic origin of the local NED frame (if any), and the
    offset added to GPS stamps to put them on the IMU clock (a receiver latency L is −L)."""

    lever_arm_b: np.ndarray = field(default_factory=lambda: np.zeros(3))
    origin_lla: tuple[float, float, float] | None = None
    time_offset_s: float = 0.0

    def __post_init__(self) -> None:
        self.lever_arm_b = np.asarray(self.lever_arm_b, dtype=float).reshape(3)


CAMERA_MODELS = {"radtan": 5, "equidistant": 4}  # lens model → number of distortion coefficients


@dataclass(slots=True)
class CameraCalibration:
    """Pinhole intrinsics, a lens model and its distortion, and mounting.

    ``model`` "radtan": radial-tangential, OpenCV order k1, k2, p1, p2, k3 (five numbers);
    "equidistant": Kannala–Brandt fisheye as ``cv2.fisheye``, k1..k4 (four numbers).
    ``distortion`` None means no distortion for either.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: np.ndarray | None = None
    R_BC: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_BC: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rate_hz: float = 7.5
    time_offset_s: float = 0.0
    model: str = "radtan"

    def __post_init__(self) -> None:
        if self.model not in CAMERA_MODELS:
            raise ValueError(f"camera model must be one of {sorted(CAMERA_MODELS)}, got {self.model!r}")
        count = CAMERA_MODELS[self.model]
        distortion = np.zeros(count) if self.distortion is None else np.asarray(self.distortion, dtype=float).ravel()
        if distortion.size != count:
            raise ValueError(f"a {self.model} camera has {count} distortion coefficients, got {distortion.size}")
        self.distortion = distortion
        self.R_BC = np.asarray(self.R_BC, dtype=float).reshape(3, 3)
        self.t_BC = np.asarray(self.t_BC, dtype=float).reshape(3)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def working(self, max_width: int) -> "CameraCalibration":
        """This camera as its frames are seen once reduced to at most ``max_width`` pixels across (0: as it is):
        :func:`working_size` wide and high, the focal lengths and the principal point (pixel centres: x' + ½ =
        s (x + ½)) scaled with them. The lens model works in normalised coordinates and the mounting in metres:
        both stay."""
        width, height = working_size(self.width, self.height, max_width)
        if width == self.width:
            return self
        sx, sy = width / self.width, height / self.height
        return replace(self, width=width, height=height, fx=self.fx * sx, fy=self.fy * sy,
                       cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5)


def working_size(width: int, height: int, max_width: int) -> tuple[int, int]:
    """A frame's size reduced, aspect kept, to at most ``max_width`` across (0, or a narrower frame: unchanged)."""
    if max_width <= 0 or width <= max_width:
        return width, height
    return max_width, max(1, round(height * max_width / width))


@dataclass(slots=True)
class Calibration:
    """Everything the estimator needs to know about the sensor set."""

    imu: ImuCalibration
    gps: GpsCalibration = field(default_factory=GpsCalibration)
    camera: CameraCalibration | None = None
    initial_heading_rad: float | None = None
    initial_heading_sigma_rad: float | None = None  # how well that heading is known (None: config default)
    truth_point_b: np.ndarray = field(default_factory=lambda: np.zeros(3))
    # The IMU's turn-on gyro bias (its datasheet's repeatability) [rad/s]: the bias prior of a start that no
    # still window measured (None: the config's init.sigma_gyro_bias)
    initial_gyro_bias_sigma: float | None = None

    def __post_init__(self) -> None:
        self.truth_point_b = np.asarray(self.truth_point_b, dtype=float).reshape(3)
