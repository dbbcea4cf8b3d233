"""The camera's mounting (``R_BC``, ``t_BC``: camera in body FRD) estimated online as filter states.

A rig's calibration is never exact. What is configured is ``R_BC⁰``, ``t_BC⁰``; the state holds corrections
``φ`` (a rotation vector) and ``c`` (metres), both in body axes, so that the mounting the filter uses is

    R_BC = Exp(φ) R_BC⁰,        t_BC = t_BC⁰ + c,

and their errors are body-side too: ``R_BC_true = Exp(δφ) R_BC``, ``t_BC_true = t_BC + δt`` (the injection
composes ``φ`` with ``δφ``, ``core.state.CalibrationLayout``). With ``h_B = Rᵀ h_W`` the landmark's direction
in the body, ``h_C = R_BCᵀ h_B`` gives

    ∂h_C/∂δφ = R_BCᵀ [h_B]× = [h_C]× R_BCᵀ,        ∂h_C/∂δt = −ρ R_BCᵀ.

A new landmark's anchor is the camera centre ``p + R t_BC`` (``∂a/∂δt = R``) and its ray ``R R_BC x``
(``∂r/∂δφ = −R [R_BC x]×``). The mounting is body-fixed: a turn of everything about world down, or a shift,
leaves it as it is, so it has no part in the camera's unobservable directions nor in the heading gauge. Like
the time offset, it has no process noise and outlives a reset with its estimate and covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from vtolpose.estimator.core import covariance
from vtolpose.estimator.core.rotation import skew, so3_exp
from vtolpose.estimator.core.state import FilterState
from vtolpose.estimator.vision.landmarks import angles_jacobian, direction

MOUNTING_DIM = 6  # [δφ, δt]


@dataclass(frozen=True, slots=True)
class MountingOptions:
    estimate: bool = False  # rotation and translation correction states while the camera is in use
    rotation_sigma_deg: float = 2.0  # their prior sigmas: how far the configured mounting may be off
    translation_sigma_m: float = 0.005

    def __post_init__(self) -> None:
        if not self.rotation_sigma_deg > 0.0:
            raise ValueError(f"camera mounting rotation sigma must be positive, got {self.rotation_sigma_deg}")
        if not self.translation_sigma_m > 0.0:
            raise ValueError(f"camera mounting translation sigma must be positive, got {self.translation_sigma_m}")


class MountingEstimate:
    """The mounting correction's estimate and covariance while no state holds it (before the map, after a reset)."""

    def __init__(self, options: MountingOptions) -> None:
        self.options = options
        self.value = np.zeros(MOUNTING_DIM)
        sigmas = np.r_[np.full(3, math.radians(options.rotation_sigma_deg)), np.full(3, options.translation_sigma_m)]
        self.cov = np.diag(sigmas**2)
        self.used = False  # a state has held it: the camera has been in use

    def attach(self, state: FilterState) -> None:
        """Give ``state`` the mounting states (after the time offset's, if any), if the option is on and it has none."""
        if not self.options.estimate or state.calib_layout.mounting:
            return
        at = state.map_start
        state.cov = covariance.insert_states(state.cov, at, self.cov)
        state.calib = np.concatenate([state.calib, self.value])
        state.calib_layout = replace(state.calib_layout, mounting=True)
        self.used = True
        if state.n_landmarks:
            _share_with_the_map(state)

    def remember(self, state: FilterState) -> None:
        """Keep what ``state`` knows of the mounting (it may be rebuilt without it)."""
        if state.calib_layout.mounting:
            self.value, self.cov = _held(state)

    def reading(self, state: FilterState | None) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
        """The correction ``[φ (rad), c (m)]`` and its six sigmas, from ``state`` if it holds them; None if never estimated."""
        if not self.used:
            return None
        value, cov = _held(state) if state is not None and state.calib_layout.mounting else (self.value, self.cov)
        return tuple(float(x) for x in value), tuple(float(x) for x in np.sqrt(np.maximum(np.diag(cov), 0.0)))


def _share_with_the_map(state: FilterState) -> None:
    """Landmarks already in the map when the mounting states come (a visual-inertial start's) were placed with the
    mounting as configured: their errors take the mounting's, ``δy ← δy + J δm``, with ``J`` as if each were placed
    now, from the pose the filter has, along its ray (their inverse depths, triangulated, are left as they are).
    Without it the map holds the configured mounting as if it were exact and pulls the estimate towards it."""
    R_WB = state.R
    R_BC = np.eye(3)  # J is taken in body axes: rays in the body, mounting rotation body-side
    rays_b = direction(state.landmarks[:, 3], state.landmarks[:, 4]) @ R_WB
    J = new_landmark_columns(R_WB, R_BC, rays_b)
    T = np.eye(state.dim)
    rows = np.arange(state.map_start, state.dim)
    T[np.ix_(rows, mounting_cols(state))] = J.reshape(-1, MOUNTING_DIM)
    state.cov = T @ state.cov @ T.T


def _held(state: FilterState) -> tuple[np.ndarray, np.ndarray]:
    cols = mounting_cols(state)
    return state.calib[state.calib_layout.rotation.start : state.calib_layout.translation.stop].copy(), state.cov[np.ix_(cols, cols)].copy()


def mounting_cols(state: FilterState) -> np.ndarray:
    """The mounting's six error-state columns ``[δφ, δt]`` (the state must hold them)."""
    start = state.robot_dim + state.calib_layout.rotation.start
    return np.arange(start, start + MOUNTING_DIM)


def mounted(state: FilterState, R_BC: np.ndarray, t_BC: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mounting the filter uses: the configured ``R_BC``, ``t_BC`` corrected by ``state``'s estimate, if it holds one."""
    layout = state.calib_layout
    if not layout.mounting:
        return R_BC, t_BC
    return so3_exp(state.calib[layout.rotation]) @ R_BC, t_BC + state.calib[layout.translation]


def measurement_columns(h_c: np.ndarray, rho: np.ndarray, R_BC: np.ndarray) -> np.ndarray:
    """``∂h_C/∂[δφ, δt] (M, 3, 6)`` of landmarks at ``h_C (M, 3)`` with inverse depths ``ρ`` (``R_BC``: the mounting used)."""
    k = len(h_c)
    J = np.empty((k, 3, MOUNTING_DIM))
    J[:, :, 0:3] = skew(h_c) @ R_BC.T
    J[:, :, 3:6] = -rho[:, None, None] * R_BC.T
    return J


def new_landmark_columns(R_WB: np.ndarray, R_BC: np.ndarray, rays_c: np.ndarray,
                         reference: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """``∂y/∂[δφ, δt] (K, 6, 6)`` of new landmarks seen along camera rays ``rays_c (K, 3)`` (``[x, y, 1]``).

    The anchor moves with the translation, the ray's angles with the rotation. ``reference``: ``(point, c_w, ρ)``
    when the inverse depths were read off a landmark at ``point`` (``1/ρ = d |x|`` with ``d = (point − c) · z``,
    the reference's depth along the optical axis ``z = R R_BC e_z`` from the camera centre ``c``): then ρ moves
    with both (``∂d/∂δt = −zᵀ R``, ``∂d/∂δφ = −(point − c)ᵀ R [R_BC e_z]×``)."""
    k = len(rays_c)
    rays_b = rays_c @ R_BC.T
    J = np.zeros((k, 6, MOUNTING_DIM))
    J[:, 0:3, 3:6] = R_WB
    J[:, 3:5, 0:3] = angles_jacobian(rays_b @ R_WB.T) @ (-R_WB @ skew(rays_b))
    if reference is not None:
        point, c_w, rho = reference
        z = R_WB @ R_BC[:, 2]
        d = float((point - c_w) @ z)
        dd = np.r_[-(point - c_w) @ R_WB @ skew(R_BC[:, 2]), -(z @ R_WB)]
        J[:, 5, :] = (-np.asarray(rho, dtype=float) / max(d, 1e-9))[:, None] * dd
    return J
