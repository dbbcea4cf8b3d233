"""The camera's residual time offset, estimated online as a filter state (OpenVINS's ``t_d``).

The runtime adds the configured ``camera.time_offset_s`` to every frame stamp; what is left of the
real offset, ``t_d``, is one more error state, between the robot and the landmarks (see
``core.state``). A frame stamped ``t`` was exposed at ``t + t_d``: the pose it saw is, to first order,

    p(t + t_d) = p + v t_d,        R(t + t_d) = R Exp(ω_B t_d) = Exp(R ω_B t_d) R

with ω_B the latest bias-corrected gyro. The global attitude error passes through unchanged, so a
landmark's Jacobians w.r.t. ``[δp, δθ]`` at the shifted pose are those of the filter's pose, and

    ∂h/∂t_d = ∂h/∂δp · v + ∂h/∂δθ · R ω_B.

(The velocity's own column, ``t_d ∂h/∂δp``, is second order in small quantities and left out: a
velocity error of 1 cm/s moves the pose 0.1 mm over 10 ms. Nor does the latest gyro, rather than the
rate over the offset, matter there: on the camera matrix's aggressive cell the first-order pose at
``t_d`` = −10 ms is 0.004° and 0.1 mm RMS from the true one, which would bias the estimate by 0.004
ms.) The
state has no process noise: the offset of a rig is constant. Its estimate outlives the map: when a
reset rebuilds the covariance for the robot alone, the camera pipeline puts the offset back with the
variance it had (its correlations, with the map that went, go too).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from vtolpose.estimator.core import covariance
from vtolpose.estimator.core.rotation import quat_mul, rotvec_quat
from vtolpose.estimator.core.state import FilterState

@dataclass(frozen=True, slots=True)
class TimeOffsetOptions:
    estimate: bool = False  # a residual offset state while the camera is in use
    sigma_s: float = 0.01  # its prior sigma: how far the configured offset may be off

    def __post_init__(self) -> None:
        if not self.sigma_s > 0.0:
            raise ValueError(f"camera time offset sigma must be positive, got {self.sigma_s}")


class TimeOffsetEstimate:
    """The offset's estimate and variance while no state holds it (before the map, after a reset)."""

    def __init__(self, options: TimeOffsetOptions) -> None:
        self.options = options
        self.value_s = 0.0
        self.variance = options.sigma_s**2
        self.used = False  # a state has held it: the camera has been in use

    def attach(self, state: FilterState) -> None:
        """Give ``state`` its offset state (first among the calibration states), if the option is on and it has none
        yet."""
        if not self.options.estimate:
            return
        self.used = True
        if state.calib_layout.time_offset:  # there already; or a visual-inertial start solved it with the window
            return
        n = state.robot_dim
        state.cov = covariance.insert_states(state.cov, n, np.array([[self.variance]]))
        state.calib = np.concatenate([[self.value_s], state.calib])
        state.calib_layout = replace(state.calib_layout, time_offset=True)

    def remember(self, state: FilterState) -> None:
        """Keep what ``state`` knows of the offset (it may be rebuilt without it)."""
        if state.calib_layout.time_offset:
            i = state.calib_layout.offset
            self.value_s = float(state.calib[i])
            self.variance = float(covariance.block_variances(state.cov, state.calib_slice)[i])

    def reading(self, state: FilterState | None) -> tuple[float, float] | None:
        """The offset's estimate and sigma [s], from ``state`` if it holds it; None if never estimated."""
        if not self.used:
            return None
        value, variance = self.value_s, self.variance
        if state is not None and state.calib_layout.time_offset:
            i = state.calib_layout.offset
            value = float(state.calib[i])
            variance = float(covariance.block_variances(state.cov, state.calib_slice)[i])
        return value, float(np.sqrt(max(variance, 0.0)))


def at_frame_time(state: FilterState, rate_b: np.ndarray) -> FilterState:
    """``state``'s nominal pose moved to the frame's instant ``t + t_d`` (a copy; the covariance shared, read only).
    ``state`` itself when it has no offset state."""
    if not state.calib_layout.time_offset:
        return state
    t_d = float(state.calib[state.calib_layout.offset])
    other = FilterState(state.layout)
    other.t_ns, other.v, other.b_g, other.b_a = state.t_ns, state.v, state.b_g, state.b_a
    other.p = state.p + state.v * t_d
    other.q = quat_mul(state.q, np.array(rotvec_quat(*(np.asarray(rate_b, dtype=float) * t_d).tolist())))
    other.landmarks, other.calib, other.calib_layout, other.cov = state.landmarks, state.calib, state.calib_layout, state.cov
    return other


def offset_column(dh_pose: np.ndarray, state: FilterState, rate_b: np.ndarray) -> np.ndarray:
    """``∂h/∂t_d (…, r, 1)`` from ``∂h/∂[δp, δθ] (…, r, 6)``: the pose's motion over the offset."""
    turn = state.R @ np.asarray(rate_b, dtype=float)
    return (dh_pose[..., 0:3] @ state.v + dh_pose[..., 3:6] @ turn)[..., None]
