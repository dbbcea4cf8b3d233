"""Unified inverse-depth landmarks (Civera, Davison & Montiel 2008) with a horizontal pole.

A landmark is ``y = [a_N, a_E, a_D, θ, φ, ρ]``: the camera centre ``a`` where it was first
seen, the direction ``m(θ, φ)`` of the ray and the inverse depth ``ρ`` along it, so that the
point is ``a + m / ρ``. The pole of (θ, φ) is horizontal (north), because a helicopter's camera
looks down and a vertical pole would be singular exactly there (spec, "State")::

    m(θ, φ) = [-sin φ, cos φ sin θ, cos φ cos θ]      (straight down: θ = φ = 0)

Initialisation is first order: the new block of the covariance is ``J_x P_xx J_xᵀ + J_z R J_zᵀ``
and its cross-covariance to everything already in the state is ``J_x P_x·`` (spec,
"Landmark initialisation"). Only the robot position and attitude enter ``J_x``.
"""

from __future__ import annotations

import numpy as np

from vtolpose.estimator.vision.camera_model import CameraModel
from vtolpose.estimator.core import covariance
from vtolpose.estimator.core.covariance import POSE
from vtolpose.estimator.core.rotation import skew
from vtolpose.estimator.core.state import LANDMARK_DIM, FilterState

ROBOT_POSE_COLS = POSE  # [δp, δθ] in every robot layout
INVERSE_DEPTH = 5  # ρ's place in a landmark's [a_N, a_E, a_D, θ, φ, ρ]


def direction(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Unit ray ``m(θ, φ)`` in NED, shape ``(..., 3)``."""
    ct, st, cp, sp = np.cos(theta), np.sin(theta), np.cos(phi), np.sin(phi)
    return np.stack([-sp, cp * st, cp * ct], axis=-1)


def direction_with_derivatives(theta: np.ndarray, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``m``, ``∂m/∂θ`` and ``∂m/∂φ``, each ``(..., 3)``, from one evaluation of the sines and cosines."""
    ct, st, cp, sp = np.cos(theta), np.sin(theta), np.cos(phi), np.sin(phi)
    zero = np.zeros_like(ct)
    return (np.stack([-sp, cp * st, cp * ct], axis=-1), np.stack([zero, cp * ct, -cp * st], axis=-1),
            np.stack([-cp, -sp * st, -sp * ct], axis=-1))


def angles(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(θ, φ) of a direction (any length): ``θ = atan2(m_E, m_D)``, ``φ = atan2(-m_N, |m_ED|)``."""
    m = np.asarray(m, dtype=float)
    return np.arctan2(m[..., 1], m[..., 2]), np.arctan2(-m[..., 0], np.hypot(m[..., 1], m[..., 2]))


def angles_jacobian(m: np.ndarray) -> np.ndarray:
    """``∂(θ, φ)/∂m``, shape ``(..., 2, 3)``; singular only for rays along the pole (north/south)."""
    m = np.asarray(m, dtype=float)
    n, e, d = m[..., 0], m[..., 1], m[..., 2]
    s = e * e + d * d
    horizontal = np.sqrt(s)
    total = n * n + s
    J = np.zeros(m.shape[:-1] + (2, 3))
    J[..., 0, 1] = d / s
    J[..., 0, 2] = -e / s
    J[..., 1, 0] = -horizontal / total
    J[..., 1, 1] = n * e / (horizontal * total)
    J[..., 1, 2] = n * d / (horizontal * total)
    return J


def landmark_points(y: np.ndarray) -> np.ndarray:
    """Euclidean points ``a + m/ρ`` of landmarks ``(M, 6)`` (ρ must be positive)."""
    y = np.asarray(y, dtype=float)
    return y[..., 0:3] + direction(y[..., 3], y[..., 4]) / y[..., 5:6]


def point_jacobian(y: np.ndarray) -> np.ndarray:
    """``∂P/∂y`` of :func:`landmark_points`, ``(M, 3, 6)``: for converting a landmark to a point."""
    y = np.asarray(y, dtype=float)
    rho = y[..., 5]
    _, dm_dt, dm_dp = direction_with_derivatives(y[..., 3], y[..., 4])
    J = np.zeros(y.shape[:-1] + (3, 6))
    J[..., :, 0:3] = np.eye(3)
    J[..., :, 3] = dm_dt / rho[..., None]
    J[..., :, 4] = dm_dp / rho[..., None]
    J[..., :, 5] = -direction(y[..., 3], y[..., 4]) / (rho * rho)[..., None]
    return J


def world_rays(R_WB: np.ndarray, R_BC: np.ndarray, camera: CameraModel, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-frame rays of pixels and their undistorted normalised coordinates."""
    xn = camera.undistort(uv)
    rays_c = np.concatenate([xn, np.ones((len(xn), 1))], axis=1)
    return rays_c @ (R_WB @ R_BC).T, xn


def initial_landmarks(
    p: np.ndarray,
    R_WB: np.ndarray,
    camera: CameraModel,
    R_BC: np.ndarray,
    t_BC: np.ndarray,
    uv: np.ndarray,
    rho0: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """New landmarks from pixels ``uv (K, 2)`` seen from pose (p, R_WB), inverse depths ``rho0``.

    Returns ``y (K, 6)``, ``J_x (K, 6, 6)`` (w.r.t. the robot error ``[δp, δθ]``) and
    ``J_z (K, 6, 3)`` (w.r.t. the pixel and the inverse-depth prior ``[u, v, ρ]``).
    The attitude error is global, ``R_true = Exp(δθ) R``: the anchor moves by
    ``-[R t_BC]× δθ`` and the ray by ``-[r_W]× δθ``.
    """
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    k = len(uv)
    anchor = p + R_WB @ t_BC
    r_w, xn = world_rays(R_WB, R_BC, camera, uv)
    theta, phi = angles(r_w)
    y = np.column_stack([np.tile(anchor, (k, 1)), theta, phi, np.asarray(rho0, dtype=float).reshape(k)])
    d_angles = angles_jacobian(r_w)  # (K, 2, 3)
    J_x = np.zeros((k, 6, 6))
    J_x[:, 0:3, 0:3] = np.eye(3)
    J_x[:, 0:3, 3:6] = -skew(R_WB @ t_BC)
    J_x[:, 3:5, 3:6] = d_angles @ -skew(r_w)
    J_z = np.zeros((k, 6, 3))
    # r_W = R R_BC [x, y, 1]: ∂r/∂(x, y) is the first two columns of R R_BC.
    dr_dxn = (R_WB @ R_BC)[:, 0:2]
    J_z[:, 3:5, 0:2] = d_angles @ dr_dxn @ camera.undistort_jacobian(xn)
    J_z[:, 5, 2] = 1.0
    return y, J_x, J_z


def add_landmarks(state: FilterState, y: np.ndarray, J_x: np.ndarray, J_z: np.ndarray, R_z: np.ndarray,
                  extra_cols: np.ndarray | None = None, J_extra: np.ndarray | None = None) -> None:
    """Append landmarks to the state with their first-order covariance.

    ``R_z (K, 3, 3)`` is the covariance of ``[u, v, ρ]`` for each new landmark. The new rows
    are ``J_x P[pose, :]`` (cross-covariance to everything), the new diagonal block is
    ``J_x P_pose J_xᵀ`` (the landmarks share the robot's error) plus ``J_z R_z J_zᵀ`` per landmark.
    ``J_extra (K, 6, E)``: what the new landmarks also take from the state columns ``extra_cols``
    (a depth prior read off a landmark already in the map), so that taking it is no new information.
    """
    k = len(y)
    if k == 0:
        return
    Jx = J_x.reshape(k * LANDMARK_DIM, 6)
    cols = ROBOT_POSE_COLS
    if extra_cols is not None and len(extra_cols):
        cols = np.concatenate([ROBOT_POSE_COLS, np.asarray(extra_cols, dtype=int)])
        Jx = np.concatenate([Jx, J_extra.reshape(k * LANDMARK_DIM, len(extra_cols))], axis=1)
    cross = Jx @ state.cov[cols, :]  # (6K, n)
    new_block = cross[:, cols] @ Jx.T
    noise = J_z @ R_z @ np.swapaxes(J_z, 1, 2)  # (K, 6, 6)
    for i in range(k):
        s = slice(LANDMARK_DIM * i, LANDMARK_DIM * (i + 1))
        new_block[s, s] += noise[i]
    state.cov = covariance.append_states(state.cov, cross, new_block)
    state.landmarks = np.vstack([state.landmarks, y])


def map_prior_jacobians(state: FilterState, R_WC: np.ndarray, c_w: np.ndarray, reference: int, rho: np.ndarray,
                        J_x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """New landmarks whose inverse depth is read off landmark ``reference``: ``1/ρ_k = d |x_k|`` with
    ``d = (P_ref − c) · z`` the reference's depth along the optical axis ``z`` from the camera centre ``c``.

    Fills the ρ row of ``J_x`` (w.r.t. ``[δp, δθ]``: ``∂d/∂δp = −z``, ``∂d/∂δθ = z × (P_ref − p)``
    with the global attitude error) and returns the reference's six columns and ``∂y_k/∂y_ref``.
    """
    y_ref = state.landmarks[reference]
    point = landmark_points(y_ref[None, :])[0]
    z = R_WC[:, 2]
    d = float((point - c_w) @ z)
    scale = -np.asarray(rho, dtype=float)[:, None] / max(d, 1e-9)  # ∂ρ/∂d = −ρ/d
    J_x[:, 5, 0:3] = scale * -z
    J_x[:, 5, 3:6] = scale * np.cross(z, point - state.p)
    J_extra = np.zeros((len(rho), LANDMARK_DIM, LANDMARK_DIM))
    J_extra[:, 5, :] = scale * (z @ point_jacobian(y_ref[None, :])[0])
    return state.map_start + LANDMARK_DIM * reference + np.arange(LANDMARK_DIM), J_extra


def baseline_significance(state: FilterState, rows: np.ndarray, t_BC: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis length of the camera's displacement since each landmark's anchor.

    The inverse depth is observable only through that displacement (the baseline). A baseline
    that is no longer than its own uncertainty is filter noise, not parallax: a depth "learnt"
    from it is an artefact of the linearisation (the measurement is bilinear in ρ and the
    camera centre). With ``δc = δp − [R t_BC]× δθ`` and the anchor's error ``δa``, the
    displacement ``d = c − a`` has covariance ``J P Jᵀ``, ``J = [I, −[R t_BC]×, −I]``.
    """
    rows = np.asarray(rows, dtype=int)
    if len(rows) == 0:
        return np.zeros(0)
    R = state.R
    d = state.p + R @ t_BC - state.landmarks[rows, 0:3]
    J = np.hstack([np.eye(3), -skew(R @ t_BC), -np.eye(3)])  # over [δp, δθ, δa]
    anchor = state.map_start + LANDMARK_DIM * rows[:, None] + np.arange(3)
    cols = np.concatenate([np.broadcast_to(ROBOT_POSE_COLS, (len(rows), 6)), anchor], axis=1)  # (K, 9)
    P = state.cov[cols[:, :, None], cols[:, None, :]]  # (K, 9, 9)
    sigma = J @ P @ J.T + np.eye(3) * 1e-12
    return np.einsum("ki,ki->k", d, np.linalg.solve(sigma, d[..., None])[..., 0])


def remove_landmarks(state: FilterState, remove: np.ndarray) -> None:
    """Delete the landmarks flagged in the boolean mask ``remove``: their 6 rows and columns go."""
    remove = np.asarray(remove, dtype=bool)
    if not np.any(remove):
        return
    keep_state = np.ones(state.dim, dtype=bool)
    keep_state[state.map_start :] = ~np.repeat(remove, LANDMARK_DIM)
    state.cov = covariance.keep_states(state.cov, keep_state)
    state.landmarks = state.landmarks[~remove]
