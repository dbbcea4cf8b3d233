"""Camera measurement model of inverse-depth landmarks (thesis eq. 4.8 times ρ) and the update.

For landmark ``y = [a, θ, φ, ρ]`` and robot pose (p, R)::

    c_W = p + R t_BC
    h_C = R_BCᵀ Rᵀ (ρ (a − c_W) + m(θ, φ))        (a direction, scale-free; ρ = 0 is fine)
    z   = π(h_C)                                   (camera model: normalise, distort, K)

Jacobians are analytic, with the global attitude error ``R_true = Exp(δθ) R``:
``∂h_C/∂δp = −ρ A``, ``∂h_C/∂δθ = A ([h_W]× + ρ [R t_BC]×)`` with ``A = R_BCᵀ Rᵀ``, and
``∂h_C/∂(a, θ, φ, ρ) = A [ρ I, ∂m/∂θ, ∂m/∂φ, a − c_W]``. Everything is batched over landmarks.
With the camera's time offset estimated (``vision.time_offset``) the pose is the one at the frame's
instant; with its mounting estimated (``vision.mounting``) ``R_BC``, ``t_BC`` are the state's estimate. The robot's
columns are ``[δp, δθ]`` and then the calibration states in the state's order (:func:`robot_cols`).
The update is the shared :func:`vtolpose.estimator.core.kalman.ekf_update` over the sparse column set of a
frame's matches, once (:func:`stacked_update`) or relinearised (:func:`iterated_update`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vtolpose.estimator.core import covariance
from vtolpose.estimator.vision.camera_model import CameraModel
from vtolpose.estimator.core.kalman import UpdateOutcome, ekf_update
from vtolpose.estimator.vision.landmarks import ROBOT_POSE_COLS, angles_jacobian, direction, direction_with_derivatives
from vtolpose.estimator.core.rotation import quat_conj, quat_log, quat_mul, skew
from vtolpose.estimator.core.state import LANDMARK_DIM, FilterState
from vtolpose.estimator.vision.mounting import measurement_columns, mounted
from vtolpose.estimator.vision.time_offset import at_frame_time, offset_column

_NO_RATE = np.zeros(3)


@dataclass(frozen=True, slots=True)
class Predictions:
    """Predicted pixels of every landmark in the state, with Jacobians and innovation covariances.

    ``H_pose (M, 2, 6 + c)`` is w.r.t. the robot's ``[δp, δθ]`` and the c calibration states (:func:`robot_cols`);
    ``H_landmark (M, 2, 6)`` w.r.t. the landmark's own six states. ``S (M, 2, 2)`` includes the pixel noise. ``in_front`` is False
    for landmarks behind the camera (their pixels are NaN), ``in_image`` for those that project
    inside the image.
    """

    uv: np.ndarray
    h_c: np.ndarray
    in_front: np.ndarray
    in_image: np.ndarray
    H_pose: np.ndarray
    H_landmark: np.ndarray
    S: np.ndarray

    def __len__(self) -> int:
        return len(self.uv)


def robot_cols(state: FilterState) -> np.ndarray:
    """The state columns a camera measurement sees besides its landmarks: ``[δp, δθ]``, then the calibration states."""
    if not state.calib.shape[0]:
        return ROBOT_POSE_COLS
    return np.concatenate([ROBOT_POSE_COLS, np.arange(state.robot_dim, state.map_start)])


def predict_h(
    state: FilterState, R_BC: np.ndarray, t_BC: np.ndarray, indices: np.ndarray | None = None, rate_b: np.ndarray = _NO_RATE,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``h_C (M, 3)``, ``h_W``, ``∂h_C/∂[δp, δθ, calibration] (M, 3, 6 + c)`` and ``∂h_C/∂y (M, 3, 6)`` (of
    landmarks ``indices`` only, if given). ``rate_b``: the bias-corrected gyro, which turns the pose over a
    time offset (used only when the state estimates one). ``R_BC``, ``t_BC``: the configured mounting (the
    state's estimate of it is used when it holds one)."""
    at = at_frame_time(state, rate_b)
    R_BC, t_BC = mounted(state, R_BC, t_BC)
    h_c, h_w, dh_pose, dh_y = _predict_h_at(at, R_BC, t_BC, indices)
    calib = []
    if state.calib_layout.time_offset:
        calib.append(offset_column(dh_pose, state, rate_b))
    if state.calib_layout.mounting:
        rho = (state.landmarks if indices is None else state.landmarks[indices])[:, 5]
        calib.append(measurement_columns(h_c, rho, R_BC))
    if calib:
        dh_pose = np.concatenate([dh_pose, *calib], axis=2)
    return h_c, h_w, dh_pose, dh_y


def _predict_h_at(
    state: FilterState, R_BC: np.ndarray, t_BC: np.ndarray, indices: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`predict_h` at the nominal pose of ``state`` as it is, w.r.t. ``[δp, δθ]`` only."""
    R = state.R
    y = state.landmarks if indices is None else state.landmarks[indices]
    A = R_BC.T @ R.T
    lever_w = R @ t_BC
    c_w = state.p + lever_w
    rho = y[:, 5]
    d = y[:, 0:3] - c_w
    m, dm_dt, dm_dp = direction_with_derivatives(y[:, 3], y[:, 4])
    h_w = rho[:, None] * d + m
    h_c = h_w @ A.T
    k = len(y)
    dh_w_pose = np.zeros((k, 3, 6))
    dh_w_pose[:, :, 0:3] = -rho[:, None, None] * np.eye(3)
    dh_w_pose[:, :, 3:6] = skew(h_w) + rho[:, None, None] * skew(lever_w)
    dh_w_y = np.empty((k, 3, 6))
    dh_w_y[:, :, 0:3] = rho[:, None, None] * np.eye(3)
    dh_w_y[:, :, 3] = dm_dt
    dh_w_y[:, :, 4] = dm_dp
    dh_w_y[:, :, 5] = d
    return h_c, h_w, A @ dh_w_pose, A @ dh_w_y


def predict(state: FilterState, camera: CameraModel, R_BC: np.ndarray, t_BC: np.ndarray, pixel_sigma: float,
            rate_b: np.ndarray = _NO_RATE) -> Predictions:
    """Predicted pixels, Jacobians and innovation covariances of all landmarks."""
    h_c, _, dh_pose, dh_y = predict_h(state, R_BC, t_BC, None, rate_b)
    uv, front, J_pi = camera.project_jacobian(h_c)
    H_pose = J_pi @ dh_pose
    H_y = J_pi @ dh_y
    S = innovation_covariances(state, H_pose, H_y, pixel_sigma)
    return Predictions(uv, h_c, front, front & camera.in_image(uv), H_pose, H_y, S)


def parallax_significance(state: FilterState, camera: CameraModel, R_BC: np.ndarray, t_BC: np.ndarray,
                          indices: np.ndarray, measured_uv: np.ndarray, pixel_sigma: float,
                          rate_b: np.ndarray = _NO_RATE) -> np.ndarray:
    """Squared Mahalanobis distance of each match from where the landmark would be seen at infinity.

    A point at infinity (``ρ = 0``) is seen along its anchor ray ``m(θ, φ)`` whatever the camera's
    translation: only the attitude moves it. A match that lies within its uncertainty of that
    prediction shows no parallax, and its depth is not observed, however far the filter believes
    the camera has moved (a believed baseline can be the filter's own drift). The covariance is the
    one of ``h(ρ = 0)`` over the attitude and the ray's angles with their correlation (both come from the
    same attitude estimates), and the pixel noise; two degrees of freedom. The calibration states (time
    offset, mounting) are taken at their estimate: matches without parallax hold them, so a test that
    waited for their sigma to narrow would wait on itself (with the mounting estimated, the hand-held
    walk then grew from 2.1 × 2.2 m to 7.2 × 4.4 m); a depth learnt under a wrong calibration is weighed
    against it by the update that learns it, which frees both.
    """
    indices = np.asarray(indices, dtype=int)
    if len(indices) == 0:
        return np.zeros(0)
    far = FilterState(state.layout)  # a view: the nominal and the covariance shared, read only
    far.t_ns, far.p, far.v, far.q, far.b_g, far.b_a = state.t_ns, state.p, state.v, state.q, state.b_g, state.b_a
    far.calib, far.calib_layout, far.cov = state.calib, state.calib_layout, state.cov
    far.landmarks = state.landmarks.copy()
    far.landmarks[indices, 5] = 0.0
    h_c, _, dh_pose, dh_y = predict_h(far, R_BC, t_BC, indices, rate_b)
    uv, _, J_pi = camera.project_jacobian(h_c)
    dh_y[:, :, 5] = 0.0  # the hypothesis fixes ρ at 0: its own uncertainty is not part of it
    S = innovation_covariances(state, J_pi @ dh_pose[:, :, 0:6], J_pi @ dh_y, pixel_sigma, ROBOT_POSE_COLS, indices)
    r = np.asarray(measured_uv, dtype=float) - uv
    chi2 = np.einsum("ki,ki->k", r, np.linalg.solve(S, r[..., None])[..., 0])
    return np.where(np.isfinite(chi2), chi2, 0.0)  # behind the camera at infinity: no verdict of parallax


def _landmark_blocks(state: FilterState, rows: np.ndarray, indices: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Robot–landmark ``(M, len(rows), 6)`` and landmark–landmark diagonal ``(M, 6, 6)`` covariance blocks, of every
    landmark or of those ``indices``."""
    r = state.map_start
    cov = state.cov
    if indices is not None:
        lm = r + LANDMARK_DIM * np.asarray(indices, dtype=int)[:, None] + np.arange(LANDMARK_DIM)  # (K, 6)
        return cov[rows[None, :, None], lm[:, None, :]], cov[lm[:, :, None], lm[:, None, :]]
    m = state.n_landmarks
    pose_rows = cov[rows, r:].reshape(len(rows), m, LANDMARK_DIM).transpose(1, 0, 2)
    lm_block = cov[r:, r:].reshape(m, LANDMARK_DIM, m, LANDMARK_DIM)
    return pose_rows, lm_block[np.arange(m), :, np.arange(m), :]


def innovation_covariances(state: FilterState, H_pose: np.ndarray, H_y: np.ndarray, pixel_sigma: float,
                           rows: np.ndarray | None = None, indices: np.ndarray | None = None) -> np.ndarray:
    """``S_i = H_i P H_iᵀ + σ² I`` for each landmark alone (the individual-compatibility test). ``H_pose`` is over the
    robot columns ``rows`` (default :func:`robot_cols`); ``indices``: the landmarks ``H_y`` is of (default all)."""
    if (state.n_landmarks if indices is None else len(indices)) == 0:
        return np.zeros((0, 2, 2))
    rows = robot_cols(state) if rows is None else np.asarray(rows)
    P_pose = state.cov[np.ix_(rows, rows)]
    P_pose_y, P_yy = _landmark_blocks(state, rows, indices)
    cross = H_pose @ P_pose_y @ np.swapaxes(H_y, 1, 2)
    S = H_pose @ P_pose @ np.swapaxes(H_pose, 1, 2) + cross + np.swapaxes(cross, 1, 2)
    S += H_y @ P_yy @ np.swapaxes(H_y, 1, 2)
    S += np.eye(2) * pixel_sigma**2
    return 0.5 * (S + np.swapaxes(S, 1, 2))


def stacked_update(
    state: FilterState, predictions: Predictions, indices: np.ndarray, measured_uv: np.ndarray, pixel_sigma: float,
    held: np.ndarray | None = None,
) -> UpdateOutcome:
    """One EKF update with the matches of a frame: landmarks ``indices`` seen at ``measured_uv``.

    The Jacobian is non-zero only in the robot's ``[δp, δθ]`` columns and the six columns of
    each matched landmark, so only those are passed to :func:`vtolpose.estimator.core.kalman.ekf_update`.
    """
    indices = np.asarray(indices, dtype=int)
    cols, H = _stacked_jacobian(state, indices, predictions.H_pose[indices], predictions.H_landmark[indices])
    H = observability_constrained(H, unobservable_directions(state, indices))
    residual = (np.asarray(measured_uv, dtype=float) - predictions.uv[indices]).reshape(-1)
    R = np.eye(len(residual)) * pixel_sigma**2
    before = heading_gauge(state)
    return _gauge_carried(state, before, ekf_update(state, cols, H, residual, R, gate=None, held=held))


def _stacked_jacobian(
    state: FilterState, indices: np.ndarray, H_pose: np.ndarray, H_landmark: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Columns touched by the matches of ``indices`` and the stacked Jacobian over them, from their
    ``(k, 2, 6)`` pose and landmark Jacobians (each landmark's block on the diagonal)."""
    k = len(indices)
    lm_cols = (state.map_start + LANDMARK_DIM * indices[:, None] + np.arange(LANDMARK_DIM)).reshape(-1)
    cols = np.concatenate([robot_cols(state), lm_cols])
    r = H_pose.shape[2]
    H = np.zeros((2 * k, r + LANDMARK_DIM * k))
    H[:, 0:r] = H_pose.reshape(2 * k, r)
    blocks = H[:, r:].reshape(k, 2, k, LANDMARK_DIM)  # a view: row pair j, landmark j
    blocks[np.arange(k), :, np.arange(k), :] = H_landmark
    return cols, H


def iterated_update(
    state: FilterState, camera: CameraModel, R_BC: np.ndarray, t_BC: np.ndarray, indices: np.ndarray,
    measured_uv: np.ndarray, pixel_sigma: float, held: np.ndarray | None = None, iterations: int = 4,
    rate_b: np.ndarray = _NO_RATE,
) -> UpdateOutcome:
    """Iterated EKF (Gauss–Newton) update with the matches of landmarks ``indices``.

    A first real baseline can move a guessed inverse depth a long way (0.1 to 1.3 m⁻¹ for a
    table under the rig); one linearisation at the guess gets the value, the robot correction
    and the variances wrong, because the measurement is bilinear in ρ and the camera centre.
    The iteration relinearises at each new estimate: ``x_{i+1} = x_0 ⊞ K_i (z − h(x_i) −
    H_i (x_0 ⊟ x_i))``. Only the state correction is computed on the way (O(n m)); the
    covariance is updated once, with the gain at the last estimate.
    """
    indices = np.asarray(indices, dtype=int)
    measured = np.asarray(measured_uv, dtype=float).reshape(-1)
    R = np.eye(len(measured)) * pixel_sigma**2

    gauge = unobservable_directions(state, indices)
    gauge_solve = _gauge_solve(gauge)  # the same every iteration
    before = heading_gauge(state)

    def linearise(at: FilterState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # Only the matched landmarks, and no innovation covariances: the gain is formed from the stack.
        h_c, _, dh_pose, dh_y = predict_h(at, R_BC, t_BC, indices, rate_b)
        uv, _, J_pi = camera.project_jacobian(h_c)
        cols, H = _stacked_jacobian(at, indices, J_pi @ dh_pose, J_pi @ dh_y)
        H = _constrained(H, gauge, gauge_solve)
        moved = np.concatenate([
            state.p - at.p,
            quat_log(quat_mul(state.q, quat_conj(at.q))),
            state.calib_layout.minus(state.calib, at.calib),
            (state.landmarks[indices] - at.landmarks[indices]).reshape(-1),
        ])
        return cols, H, measured - uv.reshape(-1) - H @ moved

    estimate = _nominal_copy(state)
    for _ in range(max(1, iterations) - 1):
        cols, H, residual = linearise(estimate)
        dx = _correction(state.cov, cols, H, residual, R, held)
        if dx is None:
            return UpdateOutcome(False, float("nan"), len(measured), "singular innovation covariance")
        new = _nominal_copy(state)
        new.inject(dx)
        step = max(np.max(np.abs(new.landmarks[indices] - estimate.landmarks[indices])), np.max(np.abs(new.p - estimate.p)))
        estimate = new
        if step < 1e-9:
            break
    cols, H, residual = linearise(estimate)
    return _gauge_carried(state, before, ekf_update(state, cols, H, residual, R, gate=None, held=held))


_DOWN = np.array([0.0, 0.0, 1.0])


def unobservable_directions(state: FilterState, indices: np.ndarray) -> np.ndarray:
    """The four directions of ``[δp, δθ, calibration, landmarks indices]`` (the columns of :func:`_stacked_jacobian`)
    that no camera measurement can see, at the prior estimate: the whole scene and vehicle shifted (3), or
    turned about world down through the origin (1) — a heading the camera is blind to. The calibration
    states take no part in either."""
    indices = np.asarray(indices, dtype=int)
    y = state.landmarks[indices]
    k = len(indices)
    r = 6 + state.calib.shape[0]
    N = np.zeros((r + LANDMARK_DIM * k, 4))
    N[0:3, 0:3] = np.eye(3)
    N[0:3, 3] = _down_cross(state.p)
    N[3:6, 3] = _DOWN
    per_landmark = N[r:].reshape(k, LANDMARK_DIM, 4)  # a view: landmark j's six rows
    for axis in range(3):
        per_landmark[:, axis, axis] = 1.0
    per_landmark[:, 0:3, 3] = _down_cross(y[:, 0:3])
    per_landmark[:, 3:5, 3] = _turned_rays(direction(y[:, 3], y[:, 4]))
    return N


def heading_gauge(state: FilterState) -> np.ndarray | None:
    """The whole error state's response to turning the vehicle and the map together about world down through
    the vehicle (per radian): what no camera measurement, nor a GPS at the vehicle, sees while it hovers.
    None without a map: nothing then for an update to carry."""
    if not state.n_landmarks:
        return None
    N = np.zeros(state.dim)
    N[state.layout.V] = _down_cross(state.v)
    N[covariance.YAW] = 1.0
    y = state.landmarks
    per_landmark = N[state.map_start:].reshape(state.n_landmarks, LANDMARK_DIM)  # a view: landmark j's six states
    per_landmark[:, 0:3] = _down_cross(y[:, 0:3] - state.p)
    per_landmark[:, 3:5] = _turned_rays(direction(y[:, 3], y[:, 4]))
    return N


def _down_cross(x: np.ndarray) -> np.ndarray:
    """``[0, 0, 1] × x`` for a vector or a stack ``(..., 3)``: the products and differences ``np.cross`` makes (the
    same bits, signed zeros included) without its general machinery, which cost a gauge a quarter of its time."""
    out = np.empty(np.shape(x))
    out[..., 0] = 0.0 * x[..., 2] - x[..., 1]
    out[..., 1] = x[..., 0] - 0.0 * x[..., 2]
    out[..., 2] = 0.0 * x[..., 1] - 0.0 * x[..., 0]
    return out


def _turned_rays(m: np.ndarray) -> np.ndarray:
    """``(θ, φ)``'s response to turning unit rays ``m (k, 3)`` about world down (per radian), ``(k, 2)``."""
    return np.einsum("kij,kj->ki", angles_jacobian(m), _down_cross(m))


def _gauge_carried(state: FilterState, before: np.ndarray | None, outcome: UpdateOutcome) -> UpdateOutcome:
    """After an accepted update: the heading gauge carried from the prior estimate to the new one."""
    if outcome.accepted:
        carry_gauge(state, before)
    return outcome


def carry_gauge(state: FilterState, before: np.ndarray | None) -> None:
    """The heading gauge carried from ``before`` (:func:`heading_gauge` at the estimate before an update) to the
    estimate now (:func:`~vtolpose.estimator.core.covariance.transfer_gauge`); the smoother's recorder told, as of
    any update. Every update that moves a state with a map needs it (a GPS fix or a rest too), or the camera's
    next update reads heading out of the move."""
    if before is None:
        return  # no map
    after = heading_gauge(state)
    if after is None or len(after) != len(before) or np.array_equal(after, before):
        return  # the map gone, or nothing moved (a refused update)
    covariance.transfer_gauge(state.cov, before, after)
    if state.observer is not None:
        state.observer.updated(state)


def observability_constrained(H: np.ndarray, N: np.ndarray) -> np.ndarray:
    """``H`` changed as little as possible (Frobenius norm) so that ``H N = 0``: a camera update then gives no
    information along the unobservable directions ``N`` of the estimate it is applied to. Jacobians
    evaluated at other points than that estimate (a relinearised iteration, landmarks and a pose that
    were each updated since) would otherwise see a little of them — a heading gained from nothing."""
    return _constrained(H, N, _gauge_solve(N))


def _gauge_solve(N: np.ndarray) -> np.ndarray:
    """``(NᵀN)⁻¹Nᵀ``, solved: the part of :func:`observability_constrained` that does not depend on ``H``."""
    return np.linalg.solve(N.T @ N, N.T)


def _constrained(H: np.ndarray, N: np.ndarray, gauge_solve: np.ndarray) -> np.ndarray:
    HN = H @ N
    return H - HN @ gauge_solve


def _nominal_copy(state: FilterState) -> FilterState:
    """The nominal values of ``state`` with its covariance shared (read only)."""
    other = FilterState(state.layout)
    other.t_ns, other.p, other.v, other.q = state.t_ns, state.p.copy(), state.v.copy(), state.q.copy()
    other.b_g, other.b_a, other.landmarks = state.b_g.copy(), state.b_a.copy(), state.landmarks.copy()
    other.calib, other.calib_layout = state.calib.copy(), state.calib_layout
    other.cov = state.cov
    return other


def _correction(cov: np.ndarray, cols: np.ndarray, H: np.ndarray, residual: np.ndarray, R: np.ndarray,
                held: np.ndarray | None) -> np.ndarray | None:
    """The Kalman correction ``K ε`` (held states get none), or None if S is not positive definite."""
    PHt = cov[:, cols] @ H.T
    S = H @ PHt[cols] + R
    try:
        L = np.linalg.cholesky(0.5 * (S + S.T))
    except np.linalg.LinAlgError:
        return None
    dx = PHt @ np.linalg.solve(L.T, np.linalg.solve(L, residual))
    if held is not None:
        dx[held] = 0.0
    return dx


def assign_state(state: FilterState, other: FilterState) -> None:
    """Make ``state`` hold ``other``'s values, in place (the estimator holds this very object)."""
    state.p, state.v, state.q, state.b_g, state.b_a = other.p, other.v, other.q, other.b_g, other.b_a
    state.landmarks, state.calib, state.calib_layout, state.cov = other.landmarks, other.calib, other.calib_layout, other.cov
