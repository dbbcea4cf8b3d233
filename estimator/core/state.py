"""Filter state: nominal values and the error-state covariance.

The covariance lives on the error state ``[δp, δv, δθ, (δb_g, δb_a), δy_1 … δy_M]``. The
attitude error is a small rotation in the *world* frame, ``R_true = Exp(δθ) R_est``, so yaw
error is simply ``δθ_D`` and the quaternion stays unit without renormalisation tricks.
The two robot variants share this code: ``thesis`` (p, v, q; 9 error states) and ``biases``
(adds gyro and accelerometer biases; 15). Landmarks occupy 6 error states each after the
robot block (see ``vtolpose.estimator.vision.landmarks``). A camera whose calibration is estimated online
puts its calibration states (``calib``, described by ``calib_layout``: the camera's residual time offset, the
error of its mounting) between the robot and the landmarks: like the map, a propagation leaves them alone
(identity transition, no process noise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from vtolpose.estimator.core.rotation import quat_conj, quat_exp, quat_log, quat_mul, quat_product, quat_to_rot, rotvec_quat

VARIANTS = ("thesis", "biases")
LANDMARK_DIM = 6


@dataclass(frozen=True, slots=True)
class StateLayout:
    """Where each robot error block sits in the covariance."""

    variant: str

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown state variant {self.variant!r}; expected one of {', '.join(VARIANTS)}")

    @property
    def estimates_biases(self) -> bool:
        return self.variant == "biases"

    @property
    def robot_dim(self) -> int:
        return 15 if self.estimates_biases else 9

    P = slice(0, 3)
    V = slice(3, 6)
    TH = slice(6, 9)
    BG = slice(9, 12)
    BA = slice(12, 15)


@dataclass(frozen=True, slots=True)
class CalibrationLayout:
    """Which camera calibration states a state holds, in this order: the time offset ``t_d`` (1 state), the
    mounting's rotation correction ``φ`` (3) and its translation correction ``δt_BC`` (3), the latter two in
    body axes (``vision.mounting``). The rotation is a rotation vector: an error ``δφ`` composes with it,
    ``Exp(φ') = Exp(δφ) Exp(φ)``, the others add."""

    time_offset: bool = False
    mounting: bool = False

    @property
    def size(self) -> int:
        return int(self.time_offset) + 6 * int(self.mounting)

    @property
    def offset(self) -> int:
        """The time offset's index in ``calib`` (it must be present)."""
        return 0

    @property
    def rotation(self) -> slice:
        """The mounting rotation's indices in ``calib`` (it must be present)."""
        start = int(self.time_offset)
        return slice(start, start + 3)

    @property
    def translation(self) -> slice:
        start = int(self.time_offset) + 3
        return slice(start, start + 3)

    def plus(self, calib: np.ndarray, dx: np.ndarray) -> np.ndarray:
        """``calib ⊞ dx``: the error ``dx`` folded into the calibration values."""
        out = calib + dx
        if self.mounting:
            r = self.rotation
            out[r] = quat_log(quat_mul(quat_exp(dx[r]), quat_exp(calib[r])))
        return out

    def minus(self, calib: np.ndarray, other: np.ndarray) -> np.ndarray:
        """``calib ⊟ other``: the error that takes ``other`` to ``calib``."""
        out = calib - other
        if self.mounting:
            r = self.rotation
            out[r] = quat_log(quat_mul(quat_exp(calib[r]), quat_conj(quat_exp(other[r]))))
        return out


NO_CALIBRATION = CalibrationLayout()


class FilterState:
    """Nominal state plus covariance; the single mutable object the filter works on.

    The nominal arrays (``p``, ``v``, ``q``, ``b_g``, ``b_a``) are replaced, never changed in place: a pose
    and the smoother's recorder keep them without a copy. The covariance is changed in place."""

    def __init__(self, layout: StateLayout) -> None:
        self.layout = layout
        self.t_ns: int = 0
        self.p = np.zeros(3)
        self.v = np.zeros(3)
        self.q = np.array([1.0, 0.0, 0.0, 0.0])
        # Biases are always present in the nominal state: the thesis variant keeps them
        # fixed at their initial calibration (e.g. the static gyro bias), the biases variant
        # estimates them.
        self.b_g = np.zeros(3)
        self.b_a = np.zeros(3)
        self.landmarks = np.zeros((0, LANDMARK_DIM))
        self.calib = np.zeros(0)  # camera calibration states, between the robot and the map
        self.calib_layout = NO_CALIBRATION  # which they are
        self.cov = np.zeros((layout.robot_dim, layout.robot_dim))
        # Told of every measurement update (``core.kalman.ekf_update``): the smoother's recorder.
        # Copies do not carry it: an update on a scratch copy is no update of the filter.
        self.observer: Any = None

    @property
    def robot_dim(self) -> int:
        return self.layout.robot_dim

    @property
    def map_start(self) -> int:
        """The first landmark's first error state: after the robot and the calibration states."""
        return self.layout.robot_dim + self.calib.shape[0]

    @property
    def calib_slice(self) -> slice:
        return slice(self.layout.robot_dim, self.map_start)

    @property
    def dim(self) -> int:
        return self.cov.shape[0]

    @property
    def n_landmarks(self) -> int:
        return self.landmarks.shape[0]

    @property
    def R(self) -> np.ndarray:
        return quat_to_rot(self.q)

    def landmark_slice(self, index: int) -> slice:
        start = self.map_start + LANDMARK_DIM * index
        return slice(start, start + LANDMARK_DIM)

    def inject(self, dx: np.ndarray) -> None:
        """Fold an error-state correction into the nominal state."""
        lay = self.layout
        self.p = self.p + dx[lay.P]
        self.v = self.v + dx[lay.V]
        # Exp(δθ) ⊗ q on plain floats (every update passes here), then normalised.
        dw, ex, ey, ez = rotvec_quat(*dx[lay.TH].tolist())
        w, x, y, z = self.q.tolist()
        q = quat_product(dw, ex, ey, ez, w, x, y, z)
        norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        self.q = np.array([q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm])
        if lay.estimates_biases:
            self.b_g = self.b_g + dx[lay.BG]
            self.b_a = self.b_a + dx[lay.BA]
        if self.calib.shape[0]:
            self.calib = self.calib_layout.plus(self.calib, dx[self.calib_slice])
        if self.n_landmarks:
            self.landmarks = self.landmarks + dx[self.map_start :].reshape(-1, LANDMARK_DIM)

    def pose_covariance(self) -> np.ndarray:
        """6 × 6 covariance of [δp, δθ] (position, then world-frame attitude error)."""
        idx = np.r_[0:3, 6:9]
        return self.cov[np.ix_(idx, idx)].copy()

    def copy(self) -> "FilterState":
        other = FilterState(self.layout)
        other.t_ns = self.t_ns
        other.p, other.v, other.q = self.p.copy(), self.v.copy(), self.q.copy()
        other.b_g, other.b_a = self.b_g.copy(), self.b_a.copy()
        other.landmarks, other.calib, other.calib_layout = self.landmarks.copy(), self.calib.copy(), self.calib_layout
        other.cov = self.cov.copy()
        return other

    def robot_only(self, cov: np.ndarray) -> None:
        """The covariance rebuilt for the robot alone (``cov``, robot_dim square): the map and the calibration
        states go with the old one (the camera pipeline keeps the calibration's estimate to put back)."""
        self.landmarks = self.landmarks[:0]
        self.calib = self.calib[:0]
        self.calib_layout = NO_CALIBRATION
        self.cov = cov

    def is_finite(self) -> bool:
        """Every nominal part (biases, calibration and landmarks included) and the covariance are finite."""
        parts = (self.p, self.v, self.q, self.b_g, self.b_a, self.calib, self.landmarks.ravel(), self.cov.ravel())
        return bool(np.isfinite(np.concatenate(parts)).all())  # one pass: a check per part costs 5 × more


STACKED_PARTS = ("p", "v", "q", "b_g", "b_a", "cov")


def stacked(states: list[FilterState]) -> tuple[np.ndarray, ...]:
    """``p``, ``v``, ``q``, ``b_g``, ``b_a`` and ``cov`` of ``states`` (one layout, no map), each as one array with
    a row per state: the form of the compiled calls that work on several states at once."""
    return tuple(np.array([getattr(s, name) for s in states]) for name in STACKED_PARTS)
