"""Frame conversions at the system's edges: NED/FRD inside, ENU/FLU (ROS REP 103) outside.

Inside vtolpose the world is local NED and the body FRD. Consumers that follow REP 103 want
ENU and FLU. Both changes are fixed proper rotations, so a pose converts as
``q_ENU_FLU = q_ENU_NED ⊗ q_NED_FRD ⊗ q_FRD_FLU``. Everything here is its own inverse.
"""

from __future__ import annotations

import numpy as np

from vtolpose.estimator.core.rotation import quat_mul, quat_normalize

# NED -> ENU swaps north and east and flips down: [e, n, u] = [n_E, n_N, -n_D].
R_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
# FRD -> FLU: a half turn about the forward axis.
R_FLU_FRD = np.diag([1.0, -1.0, -1.0])

# The same rotations as quaternions (w, x, y, z).
Q_ENU_NED = np.array([0.0, np.sqrt(0.5), np.sqrt(0.5), 0.0])
Q_FLU_FRD = np.array([0.0, 1.0, 0.0, 0.0])


def ned_to_enu(v: np.ndarray) -> np.ndarray:
    """Vector(s) in NED to ENU; works on ``[..., 3]``."""
    v = np.asarray(v, dtype=float)
    return np.stack([v[..., 1], v[..., 0], -v[..., 2]], axis=-1)


def enu_to_ned(v: np.ndarray) -> np.ndarray:
    """Vector(s) in ENU to NED (the same swap; the map is an involution)."""
    return ned_to_enu(v)


def frd_to_flu(v: np.ndarray) -> np.ndarray:
    """Body vector(s) in FRD to FLU."""
    v = np.asarray(v, dtype=float)
    return np.stack([v[..., 0], -v[..., 1], -v[..., 2]], axis=-1)


def flu_to_frd(v: np.ndarray) -> np.ndarray:
    """Body vector(s) in FLU to FRD."""
    return frd_to_flu(v)


def _edge_matrix() -> np.ndarray:
    """``q ↦ Q_ENU_NED ⊗ q ⊗ Q_FLU_FRD`` as a 4 × 4 matrix (both factors are constants), from the product itself."""
    return np.column_stack([quat_mul(quat_mul(Q_ENU_NED, e), Q_FLU_FRD) for e in np.eye(4)])


_Q_EDGE = _edge_matrix()  # one matrix product per pose instead of two quaternion products


def q_ned_frd_to_enu_flu(q_ned_frd: np.ndarray) -> np.ndarray:
    """Attitude body(FRD)→NED into body(FLU)→ENU; works on ``[..., 4]``."""
    return quat_normalize(np.asarray(q_ned_frd, dtype=float) @ _Q_EDGE.T)


def q_enu_flu_to_ned_frd(q_enu_flu: np.ndarray) -> np.ndarray:
    """Attitude body(FLU)→ENU into body(FRD)→NED (the same map: both half turns are their own inverse)."""
    return quat_normalize(np.asarray(q_enu_flu, dtype=float) @ _Q_EDGE.T)


def _block_diag(r: np.ndarray) -> np.ndarray:
    t = np.zeros((6, 6))
    t[0:3, 0:3] = r
    t[3:6, 3:6] = r
    return t


# ``diag(R, R)``: turns both 3-blocks of a 6 × 6 covariance (built once; these run for every pose).
_T_ENU_NED = _block_diag(R_ENU_NED)
_T_FLU_FRD = _block_diag(R_FLU_FRD)


def pose_covariance_ned_to_enu(cov: np.ndarray) -> np.ndarray:
    """World-frame pose covariance over ``[δp, δθ]`` from NED to ENU axes.

    The estimator's attitude error is a rotation about the *world* axes (``R_true = Exp(δθ) R``),
    which is what ROS's pose covariance means by rotation about the fixed axes of the parent
    frame; so both blocks simply turn with the world axes, and cross terms come along.
    """
    return _T_ENU_NED @ np.asarray(cov, dtype=float) @ _T_ENU_NED.T


def body_covariance_frd_to_flu(cov: np.ndarray) -> np.ndarray:
    """Body-frame covariance over ``[linear, angular]`` (a twist) from FRD to FLU axes."""
    return _T_FLU_FRD @ np.asarray(cov, dtype=float) @ _T_FLU_FRD.T


def pose_ned_frd_to_enu_flu(p_ned: np.ndarray, q_ned_frd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A pose (position in NED, attitude body FRD→NED) as REP 103 wants it: ENU position, FLU→ENU attitude."""
    return ned_to_enu(p_ned), q_ned_frd_to_enu_flu(q_ned_frd)


def pose_enu_flu_to_ned_frd(p_enu: np.ndarray, q_enu_flu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of :func:`pose_ned_frd_to_enu_flu` (for poses read from ROS data)."""
    return enu_to_ned(p_enu), q_enu_flu_to_ned_frd(q_enu_flu)
