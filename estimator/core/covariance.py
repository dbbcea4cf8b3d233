"""Covariance surgery: every change to the error-state covariance that is neither a filter step nor a
Kalman update happens here, by named block, so that nothing else indexes the covariance by hand.

A block is re-initialised when its estimate is replaced by one that owes nothing to the rest of the
state (a position taken from a fix, a velocity fitted to fixes, an attitude levelled again): its rows
and columns are zeroed and its own covariance set. The yaw is *forgotten* when the heading becomes
unknown: the frame's yaw is then a gauge, not an error, so its variance and correlations are zero.
Landmark states are appended with their cross-covariance and removed by index (EKF-SLAM's map).
"""

from __future__ import annotations

import numpy as np

from vtolpose.estimator.core import update_kernel
from vtolpose.estimator.core.state import LANDMARK_DIM, StateLayout

P, V, TH, BG, BA = StateLayout.P, StateLayout.V, StateLayout.TH, StateLayout.BG, StateLayout.BA
YAW = 8  # δθ_D: the yaw error in the world frame
NAV = slice(0, 9)  # δp, δv, δθ: the navigation blocks both state models share
POSE = np.r_[0:3, 6:9]  # [δp, δθ] within [δp, δv, δθ]


def reinitialise(cov: np.ndarray, block: slice, block_cov: np.ndarray) -> None:
    """``block`` re-initialised in place: uncorrelated with the rest, its own covariance ``block_cov``."""
    cov[block, :] = 0.0
    cov[:, block] = 0.0
    cov[block, block] = block_cov


def decorrelate(cov: np.ndarray, block: slice) -> None:
    """``block``'s rows and columns zeroed in place (its own covariance too): the caller sets what it knows."""
    cov[block, :] = 0.0
    cov[:, block] = 0.0


def forget_yaw(cov: np.ndarray) -> None:
    """The heading becomes unknown: the frame's yaw is a gauge, its variance and correlations zero (in each of a
    stack of covariances too: the last two axes)."""
    cov[..., YAW, :] = 0.0
    cov[..., :, YAW] = 0.0


def transfer_gauge(cov: np.ndarray, before: np.ndarray, after: np.ndarray) -> None:
    """The heading gauge's direction moved from ``before`` to ``after`` (the error state's response to a turn of
    everything about world down, at the estimates before and after an update that moved them), in place:
    ``P ← T P Tᵀ`` with ``T = I + (after − before) e_ψᵀ``, so that the uncertainty the update left along the
    turn it was blind to is carried to the turn at the new estimate. Without it the next update, blind to the
    turn at its own estimate, reads a little heading out of the mismatch (EKF-SLAM's inconsistency; this is
    the observability-constrained transition of OC-EKF, applied where the estimate moves)."""
    d = np.subtract(after, before, dtype=float)
    if cov.flags.c_contiguous and cov.dtype == np.float64:
        update_kernel.gauge_transfer(cov, d, YAW)  # the same arithmetic, one compiled pass
        return
    c = cov[:, YAW].copy()
    cov += np.outer(d, c) + np.outer(c, d) + cov[YAW, YAW] * np.outer(d, d)


def block_variances(cov: np.ndarray, block: slice) -> np.ndarray:
    """The diagonal of ``block`` (a copy)."""
    return np.diagonal(cov)[block].copy()


def robot_reset(layout: StateLayout, var_p: np.ndarray, sigma_velocity: float, sigma_attitude: float,
                sigma_gyro_bias: float, sigma_accel_bias: float) -> np.ndarray:
    """A robot covariance rebuilt after a reset: the position's variances kept, the rest a start in motion's
    sigmas, every block uncorrelated (what survives a reset is only what is known to be sound)."""
    sigmas = [sigma_velocity] * 3 + [sigma_attitude] * 3
    if layout.estimates_biases:
        sigmas += [sigma_gyro_bias] * 3 + [sigma_accel_bias] * 3
    return np.diag(np.concatenate([var_p, np.square(sigmas)]))


def nav_block(cov: np.ndarray) -> np.ndarray:
    """A copy of the ``[δp, δv, δθ]`` covariance (9 × 9; of each of a stack of covariances: the last two axes)."""
    return cov[..., NAV, NAV].copy()


def robot_block(cov: np.ndarray, robot_dim: int) -> np.ndarray:
    """A copy of the leading ``robot_dim`` states' covariance: landmarks left out, and bias states too where a
    model without them takes a state from one that has them."""
    return cov[:robot_dim, :robot_dim].copy()


def robot_and_map(cov: np.ndarray, full_robot_dim: int, robot_dim: int) -> np.ndarray:
    """``cov`` (a ``full_robot_dim`` robot, then landmarks) for a model whose robot has ``robot_dim`` states:
    the robot's leading states and every landmark state kept."""
    keep = np.r_[0:robot_dim, full_robot_dim : len(cov)]
    return cov[np.ix_(keep, keep)].copy()


def landmark_sigmas(cov: np.ndarray, robot_dim: int, component: int) -> np.ndarray:
    """Each landmark's standard deviation in one of its ``LANDMARK_DIM`` components (5: the inverse depth)."""
    return np.sqrt(np.diag(cov)[robot_dim + component :: LANDMARK_DIM])


def pose_block(cov: np.ndarray) -> np.ndarray:
    """The ``[δp, δθ]`` covariance (6 × 6) out of a ``[δp, δv, δθ, ...]`` one."""
    return cov[np.ix_(POSE, POSE)]


def append_states(cov: np.ndarray, cross: np.ndarray, new_block: np.ndarray) -> np.ndarray:
    """``cov`` grown by states whose cross-covariance to the existing ones is ``cross`` (k × n) and whose own
    covariance is ``new_block`` (k × k, symmetrised here)."""
    n, k = cov.shape[0], new_block.shape[0]
    out = np.empty((n + k, n + k))
    out[:n, :n] = cov
    out[n:, :n] = cross
    out[:n, n:] = cross.T
    out[n:, n:] = 0.5 * (new_block + new_block.T)
    return out


def keep_states(cov: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """``cov`` restricted to the states ``keep`` selects (a boolean mask or indices): states removed."""
    return cov[np.ix_(keep, keep)]


def insert_states(cov: np.ndarray, at: int, new_block: np.ndarray) -> np.ndarray:
    """``cov`` with states inserted before index ``at``, uncorrelated with the rest, their own covariance
    ``new_block`` (k × k): calibration states put between the robot and the map."""
    n, k = cov.shape[0], new_block.shape[0]
    old = np.r_[0:at, at + k : n + k]
    out = np.zeros((n + k, n + k))
    out[np.ix_(old, old)] = cov
    out[at : at + k, at : at + k] = new_block
    return out
