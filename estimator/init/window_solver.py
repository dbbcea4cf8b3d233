"""Gravity, velocity, biases and metric structure from a window of feature tracks and IMU deltas.

Everything is expressed in the IMU body frame at the window's first frame (B0), with the IMU
there at the origin. The gyro (with bias ``b_g``) gives the rotation ``R_k`` from frame k's
body to B0; the accelerometer gives, through the strapdown integrals ``S, M, V, MV`` of
``vtolpose.estimator.inertial.motion_alignment.integrate``, the IMU's path up to the unknown
first velocity ``v0``, gravity ``g`` (B0) and accelerometer bias ``b_a``::

    p_k = v0 τ_k + ½ g τ_k² + S_k − M_k b_a

A point ``f_j`` (B0) seen by frame k along the undistorted ray ``x = [x, y, 1]`` lies on it:
``w × (f_j − c_k) = 0`` with ``w = R_k R_BC x`` and the camera centre ``c_k = p_k + R_k t_BC``.
With ``b_a = 0`` and ``b_g`` at its prior the first guess is linear: the structure up to
scale from the rays alone (the rotations are known), then scale, ``v0`` and ``g`` from the
camera centres against the IMU's path; a solved ``|g|`` far from gravity says the window had
too little motion. Then damped Gauss–Newton refines
``[tilt of g (2), b_g, b_a, p_1…p_{K−1}, v_0…v_{K−1}, f]`` with ``|g|`` fixed, against the pixel
residuals, the IMU's position and velocity increments between frames (with the white-noise
covariance of the accelerometer and of gravity turned by the gyro's angle random walk) and
the bias priors. The inverse of its information matrix is the window's covariance.

With ``sigma_time_offset`` set, the camera's residual time offset ``t_d`` is one more unknown
(prior ``N(time_offset_prior, σ²)``), as in the filter (``vision.time_offset``): frame k, stamped ``τ_k``, was
exposed at ``τ_k + t_d``, when the body was at ``p_k + v_k t_d`` turned by ``Exp(ω_k t_d)``, with
``ω_k`` the bias-corrected gyro of the IMU step that ends at ``τ_k``. Solved with the configured
offset taken as exact, a wrong one bends the window's path and gravity to fit it; the filter then
starts from that bent state with a covariance that does not know why.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vtolpose.estimator.core.rotation import skew, so3_exp, so3_log
from vtolpose.estimator.inertial.motion_alignment import integrate


@dataclass(frozen=True, slots=True)
class WindowProblem:
    """A window: frame times τ (s, frame 0 at 0), observations, IMU deltas, camera and priors."""

    frame_t: np.ndarray  # (K,)
    obs_frame: np.ndarray  # (N,) frame index of each observation
    obs_point: np.ndarray  # (N,) point index
    obs_xn: np.ndarray  # (N, 2) undistorted normalised coordinates
    imu_t: np.ndarray  # (n + 1,) delta boundaries, s, same clock as frame_t
    dtheta: np.ndarray  # (n, 3)
    dvel: np.ndarray  # (n, 3)
    R_BC: np.ndarray
    t_BC: np.ndarray
    focal_px: float
    pixel_sigma: float
    gravity: float
    accel_noise: float  # m/s²/√Hz
    gyro_noise: float  # rad/s/√Hz
    bias_g: np.ndarray  # prior mean
    sigma_bias_g: float
    sigma_bias_a: float
    time_offset_prior: float = 0.0  # s, the camera's residual offset as known before the window
    sigma_time_offset: float = 0.0  # s, its sigma; 0: not solved (the prior taken as exact)

    @property
    def solves_time_offset(self) -> bool:
        return self.sigma_time_offset > 0.0

    @property
    def n_frames(self) -> int:
        return len(self.frame_t)

    @property
    def n_points(self) -> int:
        return int(self.obs_point.max()) + 1 if len(self.obs_point) else 0


@dataclass(frozen=True, slots=True)
class WindowSolution:
    """The refined window; ``cov`` over the refinement's unknowns (see :class:`Layout`)."""

    gravity_dir: np.ndarray  # unit, B0
    bias_g: np.ndarray
    bias_a: np.ndarray
    p: np.ndarray  # (K, 3) IMU positions, B0
    v: np.ndarray  # (K, 3)
    R: np.ndarray  # (K, 3, 3) body k → B0
    points: np.ndarray  # (M, 3) B0
    cov: np.ndarray
    tangent: np.ndarray  # (3, 2) basis of the gravity tilt the covariance is over
    residual_ratio: float  # RMS of the whitened residuals
    linear_gravity: float  # |g| of the linear first guess
    inliers: np.ndarray  # (N,) observations kept
    iterations: int
    time_offset: float = 0.0  # s, the camera's residual offset (0 when not solved)


@dataclass(frozen=True, slots=True)
class Layout:
    """Where each unknown of the refinement sits: the camera's time offset, when solved, after the velocities."""

    n_frames: int
    n_points: int
    time_offset: bool = False

    @classmethod
    def of(cls, problem: WindowProblem) -> "Layout":
        return cls(problem.n_frames, problem.n_points, problem.solves_time_offset)

    G = slice(0, 2)
    BG = slice(2, 5)
    BA = slice(5, 8)

    def p(self, k: int) -> slice:  # k >= 1 (p_0 is the origin)
        return slice(8 + 3 * (k - 1), 8 + 3 * k)

    def v(self, k: int) -> slice:
        start = 8 + 3 * (self.n_frames - 1)
        return slice(start + 3 * k, start + 3 * k + 3)

    @property
    def TD(self) -> slice:  # empty when the offset is not solved
        start = 8 + 6 * self.n_frames - 3
        return slice(start, start + int(self.time_offset))

    def point(self, j: int) -> slice:
        start = self.TD.stop
        return slice(start + 3 * j, start + 3 * j + 3)

    @property
    def size(self) -> int:
        return self.TD.stop + 3 * self.n_points


class WindowFailure(Exception):
    """The window does not determine the start (too little motion, too few points, no convergence).

    ``check`` names the test that failed in one word (``tracks``, ``motion``, ``information``,
    ``scale``, ...): what a status line and an operator's text can group by."""

    def __init__(self, message: str, check: str) -> None:
        super().__init__(message)
        self.check = check


def tangent_basis(u: np.ndarray) -> np.ndarray:
    """Two unit vectors orthogonal to the unit vector ``u`` and to each other, as columns."""
    a = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    b1 = np.cross(u, a)
    b1 /= np.linalg.norm(b1)
    return np.column_stack([b1, np.cross(u, b1)])


def _integrals(problem: WindowProblem, b_g: np.ndarray):
    return integrate(problem.imu_t, problem.dtheta, problem.dvel, b_g, problem.frame_t)


def frame_rates(problem: WindowProblem, b_g: np.ndarray) -> np.ndarray:
    """``(K, 3)``: the bias-corrected gyro at each frame, that of the IMU step ending at its stamp (the first
    frame's: the step starting there), as the filter turns a frame's pose by its latest gyro."""
    step = np.clip(np.searchsorted(problem.imu_t, problem.frame_t, side="left") - 1, 0, len(problem.dtheta) - 1)
    return problem.dtheta[step] / np.diff(problem.imu_t)[step, None] - b_g


def exposure_bodies(problem: WindowProblem, est: "_Estimate", R: np.ndarray, k: np.ndarray, j: np.ndarray,
                    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Points ``j`` in the body of frame ``k`` at its exposure ``τ_k + t_d``: ``Exp(ω_k t_d)ᵀ u`` with
    ``u = R_kᵀ (f_j − p_k − v_k t_d)``. Returns ``(d, u, Exp(ω_k t_d))``; without the offset solved, ``d = u``
    at ``τ_k`` and the other two are None."""
    if not problem.solves_time_offset:
        return np.einsum("nba,nb->na", R[k], est.f[j] - est.p[k]), None, None
    turn = so3_exp(frame_rates(problem, est.b_g) * est.t_d)[k]
    u = np.einsum("nba,nb->na", R[k], est.f[j] - est.p[k] - est.v[k] * est.t_d)
    return np.einsum("nba,nb->na", turn, u), u, turn


def _rays(problem: WindowProblem, R: np.ndarray) -> np.ndarray:
    """Unit rays of the observations in B0."""
    rays = np.column_stack([problem.obs_xn, np.ones(len(problem.obs_xn))])
    w = np.einsum("nab,bc,nc->na", R[problem.obs_frame], problem.R_BC, rays)
    return w / np.linalg.norm(w, axis=1, keepdims=True)


def pair_directions(problem: WindowProblem, R: np.ndarray, min_shared: int = 8) -> list[tuple[int, int, np.ndarray]]:
    """``(a, b, t̂)``: the direction of the camera's motion from frame a to the next frame b, in B0.

    With the rotations known, every point seen in both frames puts the baseline in the plane of
    its two rays, i.e. orthogonal to their normal ``w_a × w_b``; the baseline is the direction
    most orthogonal to all of them (the smallest eigenvector of ``Σ n nᵀ``), its sign the one
    that puts the points in front of both cameras.
    """
    w = _rays(problem, R)
    out = []
    frames = [dict(zip(problem.obs_point[problem.obs_frame == k].tolist(), w[problem.obs_frame == k]))
              for k in range(problem.n_frames)]
    for a in range(problem.n_frames - 1):
        b = a + 1
        shared = sorted(set(frames[a]) & set(frames[b]))
        if len(shared) < min_shared:
            continue
        wa = np.array([frames[a][j] for j in shared])
        wb = np.array([frames[b][j] for j in shared])
        n = np.cross(wa, wb)
        t = np.linalg.eigh(n.T @ n)[1][:, 0]
        # Once more without the points far off that plane (a wrong track).
        off = np.abs(n @ t)
        keep = off <= 3.0 * max(float(np.median(off)), 1e-12)
        if np.sum(keep) >= min_shared:
            wa, wb, n = wa[keep], wb[keep], n[keep]
            t = np.linalg.eigh(n.T @ n)[1][:, 0]
        # Depths along both rays for baseline t: wa λa − wb λb = t; the majority must be positive.
        M = np.stack([wa, -wb], axis=2)  # (S, 3, 2)
        depths = np.einsum("sij,sj->si", np.linalg.pinv(M), np.broadcast_to(t, wa.shape))
        if np.sum(np.all(depths > 0.0, axis=1)) < np.sum(np.all(depths < 0.0, axis=1)):
            t = -t
        out.append((a, b, t))
    return out


def acceleration_spread(problem: WindowProblem) -> float:
    """RMS of the vehicle's acceleration about its mean over the window (m/s²), from the IMU alone.

    Gravity is constant in B0, so the spread of the rotated specific force between frames is
    the spread of the acceleration itself: without it (a steady cruise) nothing fixes the scale.
    """
    ints = _integrals(problem, problem.bias_g)
    mean_force = np.diff(ints.V, axis=0) / np.diff(problem.frame_t)[:, None]
    return float(np.sqrt(np.mean(np.sum((mean_force - mean_force.mean(axis=0)) ** 2, axis=1))))


def _camera_path(problem: WindowProblem, ints, v0: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Camera centres in B0 for a first velocity and gravity (``b_a = 0``)."""
    tau = problem.frame_t
    return np.outer(tau, v0) + 0.5 * np.outer(tau * tau, g) + ints.S + ints.R @ problem.t_BC


def linear_guess(problem: WindowProblem, b_g: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(v0, g, baselines)`` from the visual motion directions and the IMU's path (``b_a = 0``).

    The camera moves from frame a to b by ``λ t̂`` (vision gives t̂, not its length λ) and by
    ``v0 (τ_b − τ_a) + ½ g (τ_b² − τ_a²) + S_b − S_a + (R_b − R_a) t_BC`` (the IMU): linear in
    ``(v0, g, λ…)``, and metric from the start — no structure that could shrink onto the cameras.
    """
    ints = _integrals(problem, problem.bias_g if b_g is None else b_g)
    pairs = pair_directions(problem, ints.R)
    if len(pairs) < 3:
        raise WindowFailure(f"{len(pairs)} pairs of frames share enough points", "tracks")
    rows, rhs = _alignment_rows(problem, ints, pairs, with_gravity=True)
    sol, *_ = np.linalg.lstsq(rows, rhs, rcond=None)
    return sol[0:3], sol[3:6], sol[6:]


def _alignment_rows(problem: WindowProblem, ints, pairs, with_gravity: bool) -> tuple[np.ndarray, np.ndarray]:
    tau = problem.frame_t
    n_g = 3 if with_gravity else 0
    rows = np.zeros((3 * len(pairs), 3 + n_g + len(pairs)))
    rhs = np.zeros(3 * len(pairs))
    for i, (a, b, t) in enumerate(pairs):
        r = slice(3 * i, 3 * i + 3)
        rows[r, 0:3] = -np.eye(3) * (tau[b] - tau[a])
        if with_gravity:
            rows[r, 3:6] = -np.eye(3) * 0.5 * (tau[b] ** 2 - tau[a] ** 2)
        rows[r, 3 + n_g + i] = t
        rhs[r] = ints.S[b] - ints.S[a] + (ints.R[b] - ints.R[a]) @ problem.t_BC
    return rows, rhs


def scale_given_gravity(problem: WindowProblem, g_dir: np.ndarray, b_g: np.ndarray | None = None,
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(v0, gravity direction, baselines, b_a)`` with ``|g|`` held at gravity's magnitude.

    Over a short window a steady acceleration (a turn) looks like a tilted gravity; only the
    magnitude of gravity tells them apart, so the alignment is repeated with ``|g|`` fixed, its
    direction found by Gauss–Newton on the sphere (``v0``, ``b_a`` and the baselines solved
    exactly for each direction), starting from ``g_dir``. The accelerometer bias is in it because
    with ``|g|`` fixed nothing else can take a consumer accelerometer's error along gravity (a
    few tenths of m/s²: metres over a window, more than a gentle path moves); its prior
    (``sigma_bias_a``, weighed as a centimetre of misfit per sigma) holds the directions in which a
    window that barely turns cannot tell it from the tilt.
    """
    ints = _integrals(problem, problem.bias_g if b_g is None else b_g)
    pairs = pair_directions(problem, ints.R)
    motion, base = _alignment_rows(problem, ints, pairs, with_gravity=False)
    n = len(pairs)
    bias_cols = np.vstack([ints.M[b] - ints.M[a] for a, b, _ in pairs])  # p carries −M b_a
    prior = np.eye(3) * (0.01 / max(problem.sigma_bias_a, 1e-6))
    rows = np.vstack([np.hstack([motion[:, :3], bias_cols, motion[:, 3:]]), np.hstack([np.zeros((3, 3)), prior, np.zeros((3, n))])])
    base = np.concatenate([base, np.zeros(3)])
    tau = problem.frame_t
    half = np.concatenate([np.concatenate([np.full(3, 0.5 * (tau[b] ** 2 - tau[a] ** 2)) for a, b, _ in pairs]), np.zeros(3)])

    def fit(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rhs = base + half * np.tile(problem.gravity * direction, n + 1)
        sol, *_ = np.linalg.lstsq(rows, rhs, rcond=None)
        return sol, rows @ sol - rhs

    direction = g_dir / np.linalg.norm(g_dir)
    sol, r = fit(direction)
    for _ in range(20):
        basis = tangent_basis(direction)
        J = np.column_stack([(fit(so3_exp(basis[:, i] * 1e-6) @ direction)[1] - r) / 1e-6 for i in range(2)])
        step, *_ = np.linalg.lstsq(J, -r, rcond=None)
        candidate = so3_exp(basis @ step) @ direction
        new_sol, new_r = fit(candidate)
        if float(new_r @ new_r) >= float(r @ r):
            break
        direction, sol, r = candidate, new_sol, new_r
        if np.linalg.norm(step) < 1e-9:
            break
    return sol[0:3], direction, sol[6:], sol[3:6]


def triangulate(problem: WindowProblem, R: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Each point nearest (least squares, in metres) to all its rays from the given camera centres."""
    w = _rays(problem, R)
    P = np.eye(3) - w[:, :, None] * w[:, None, :]  # projects out the ray
    A = np.zeros((problem.n_points, 3, 3))
    b = np.zeros((problem.n_points, 3))
    np.add.at(A, problem.obs_point, P)
    np.add.at(b, problem.obs_point, np.einsum("nab,nb->na", P, centres[problem.obs_frame]))
    return np.linalg.solve(A + np.eye(3) * 1e-9, b[..., None])[..., 0]


@dataclass(slots=True)
class _Estimate:
    g_dir: np.ndarray
    b_g: np.ndarray
    b_a: np.ndarray
    p: np.ndarray  # (K, 3), p[0] = 0
    v: np.ndarray
    f: np.ndarray
    t_d: float = 0.0  # the camera's residual time offset

    def moved(self, dx: np.ndarray, lay: Layout, tangent: np.ndarray) -> "_Estimate":
        p = self.p.copy()
        p[1:] += dx[lay.p(1).start : lay.v(0).start].reshape(-1, 3)
        g_dir = so3_exp(tangent @ dx[lay.G]) @ self.g_dir
        return _Estimate(g_dir / np.linalg.norm(g_dir), self.b_g + dx[lay.BG], self.b_a + dx[lay.BA], p,
                         self.v + dx[lay.v(0).start : lay.v(lay.n_frames - 1).stop].reshape(-1, 3),
                         self.f + dx[lay.point(0).start :].reshape(-1, 3), self.t_d + float(np.sum(dx[lay.TD])))


class _Linearised:
    """Residuals and Jacobians of one linearisation; the points enter only the pixel rows, three
    columns each, so the normal equations are solved with the points eliminated (Schur complement)."""

    def __init__(self, n_points: int, n_c: int) -> None:
        self.n_points, self.n_c = n_points, n_c
        self.r_pix = np.zeros((0, 2))
        self.frame = self.point = np.zeros(0, dtype=int)
        self.J_bg = self.J_f = self.J_p = np.zeros((0, 2, 3))
        self.J_v = self.J_td = None  # with the time offset solved: each pixel's v_k and t_d columns
        self.r_dense = np.zeros(0)
        self.J_dense = np.zeros((0, n_c))

    def chi2(self) -> np.ndarray:
        return np.sum(self.r_pix**2, axis=1)

    def normal_equations(self, weights: np.ndarray, lay: Layout) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``H_cc, H_cf (n_c, 3M), H_ff (M, 3, 3), g_c, g_f`` of the (weighted) least squares."""
        n_c, M = self.n_c, self.n_points
        w = weights[:, None, None]
        H_cc = self.J_dense.T @ self.J_dense
        g_c = self.J_dense.T @ self.r_dense
        # Pose columns of each pixel row: b_g, and p_k unless k = 0 (then v_k and t_d when the offset is solved).
        blocks = [self.J_bg, self.J_p] if self.J_v is None else [self.J_bg, self.J_p, self.J_v, self.J_td]
        Jc = np.concatenate(blocks, axis=2)  # (n, 2, 6 or 10)
        cols = np.zeros((len(self.frame), Jc.shape[2]), dtype=int)
        cols[:, 0:3] = np.arange(lay.BG.start, lay.BG.stop)
        cols[:, 3:6] = lay.p(1).start + 3 * (self.frame[:, None] - 1) + np.arange(3)
        has_p = self.frame >= 1
        mask = np.ones(cols.shape, bool)
        mask[:, 3:6] = has_p[:, None]
        if self.J_v is not None:
            cols[:, 6:9] = lay.v(0).start + 3 * self.frame[:, None] + np.arange(3)
            cols[:, 9] = lay.TD.start
        Jc = Jc * mask[:, None, :]
        cols = np.where(mask, cols, 0)
        JtJ = np.einsum("nai,naj->nij", Jc, Jc * w)
        np.add.at(H_cc, (cols[:, :, None], cols[:, None, :]), JtJ)
        np.add.at(g_c, cols, np.einsum("nai,na->ni", Jc, self.r_pix * weights[:, None]))
        H_cf = np.zeros((n_c, 3 * M))
        fcols = 3 * self.point[:, None] + np.arange(3)
        np.add.at(H_cf, (cols[:, :, None], fcols[:, None, :]), np.einsum("nai,naj->nij", Jc, self.J_f * w))
        H_ff = np.zeros((M, 3, 3))
        np.add.at(H_ff, self.point, np.einsum("nai,naj->nij", self.J_f, self.J_f * w))
        g_f = np.zeros((M, 3))
        np.add.at(g_f, self.point, np.einsum("nai,na->ni", self.J_f, self.r_pix * weights[:, None]))
        return H_cc, H_cf, H_ff, g_c, g_f.reshape(-1)


def _solve_normal(H_cc, H_cf, H_ff, g_c, g_f, damping: float) -> np.ndarray:
    """The Gauss–Newton step ``−H⁻¹ g`` (Levenberg–Marquardt damped), points eliminated first."""
    M = len(H_ff)
    A = H_cc + damping * np.diag(np.diag(H_cc) + 1e-9)
    D = H_ff + damping * (H_ff * np.eye(3) + np.eye(3) * 1e-9)
    D_inv = np.linalg.inv(D)  # (M, 3, 3)
    B = H_cf.reshape(len(g_c), M, 3)
    BD = np.einsum("cmi,mij->cmj", B, D_inv)
    S = A - BD.reshape(len(g_c), -1) @ H_cf.T
    rhs = g_c - BD.reshape(len(g_c), -1) @ g_f
    dx_c = np.linalg.solve(S, rhs)
    dx_f = np.einsum("mij,mj->mi", D_inv, g_f.reshape(M, 3) - np.einsum("cmi,c->mi", B, dx_c))
    return -np.concatenate([dx_c, dx_f.reshape(-1)])


def _covariance(H_cc, H_cf, H_ff) -> np.ndarray:
    """The inverse of the normal matrix, assembled from its Schur complement."""
    M = len(H_ff)
    n_c = len(H_cc)
    D_inv = np.linalg.inv(H_ff)
    B = H_cf.reshape(n_c, M, 3)
    BD = np.einsum("cmi,mij->cmj", B, D_inv).reshape(n_c, -1)
    S_inv = np.linalg.inv(H_cc - BD @ H_cf.T)
    cov = np.zeros((n_c + 3 * M, n_c + 3 * M))
    cov[:n_c, :n_c] = S_inv
    cross = -S_inv @ BD
    cov[:n_c, n_c:] = cross
    cov[n_c:, :n_c] = cross.T
    ff = BD.T @ S_inv @ BD
    for m in range(M):
        ff[3 * m : 3 * m + 3, 3 * m : 3 * m + 3] += D_inv[m]
    cov[n_c:, n_c:] = ff
    return 0.5 * (cov + cov.T)


class _Residuals:
    """Whitened residuals and Jacobian of the refinement at one estimate."""

    def __init__(self, problem: WindowProblem, inliers: np.ndarray) -> None:
        self.problem = problem
        self.inliers = inliers
        dt = np.diff(problem.frame_t)
        # White accelerometer noise, plus gravity turned by the gyro's angle random walk over the
        # window (a correlated error, taken here as white of the same size).
        q = max(problem.accel_noise**2 + (problem.gravity * problem.gyro_noise) ** 2 * problem.frame_t[-1], 1e-8)
        self.imu_sqrt_info = []
        for d in dt:
            cov = q * np.array([[d**3 / 3.0, d**2 / 2.0], [d**2 / 2.0, d]])
            L = np.linalg.cholesky(cov) if d > 0 else None
            assert L is not None, (d, problem.frame_t)
            self.imu_sqrt_info.append(np.kron(np.linalg.inv(L), np.eye(3)))  # whitens [r_p; r_v]

    def evaluate(self, est: _Estimate, tangent: np.ndarray, jacobian: bool = True) -> "_Linearised":
        """Whitened residuals (pixels, then IMU increments and bias priors) and, with ``jacobian``,
        their Jacobians in the sparse form the normal equations need."""
        pr = self.problem
        K, M = pr.n_frames, pr.n_points
        lay = Layout.of(pr)
        n_c = lay.point(0).start  # everything but the points
        eps = 1e-6
        b_batch = est.b_g + np.vstack([np.zeros(3), eps * np.eye(3)]) if jacobian else est.b_g[None, :]
        ints = integrate(pr.imu_t, pr.dtheta, pr.dvel, b_batch, pr.frame_t)  # leading axis: nominal, +x, +y, +z
        R = ints.R[0]
        g = pr.gravity * est.g_dir
        out = _Linearised(M, n_c)
        # Pixels.
        obs = np.flatnonzero(self.inliers)
        k, j = pr.obs_frame[obs], pr.obs_point[obs]
        scale = pr.focal_px / pr.pixel_sigma
        d, u, turn = exposure_bodies(pr, est, R, k, j)  # body k (at its exposure)
        h = (d - pr.t_BC) @ pr.R_BC  # camera k: R_BCᵀ (d − t_BC)
        z = h[:, 0:2] / h[:, 2:3]
        out.r_pix = (z - pr.obs_xn[obs]) * scale
        out.frame, out.point = k, j
        if jacobian:
            n = len(obs)
            Jz = np.zeros((n, 2, 3))
            Jz[:, 0, 0] = Jz[:, 1, 1] = 1.0 / h[:, 2]
            Jz[:, :, 2] = -z / h[:, 2:3]
            A = Jz @ pr.R_BC.T * scale  # ∂z/∂d, whitened
            # R_k(b + δ) = R_k Exp(J_k δ): J_k column i from the perturbed integration.
            Jrot = np.stack([np.stack([so3_log(R[kk].T @ ints.R[1 + i][kk]) / eps for i in range(3)], axis=1)
                             for kk in range(K)])
            if turn is None:
                out.J_bg = A @ skew(d) @ Jrot[k]
                out.J_f = A @ np.swapaxes(R[k], 1, 2)
            else:  # d = Exp(ω t_d)ᵀ u, ω = gyro − b_g: the bias turns u and, over t_d, the exposure's turn
                turn_t = np.swapaxes(turn, 1, 2)
                out.J_bg = A @ (turn_t @ skew(u) @ Jrot[k] - est.t_d * skew(d))
                out.J_f = A @ turn_t @ np.swapaxes(R[k], 1, 2)
                out.J_v = -est.t_d * out.J_f
                # ∂d/∂t_d = −ω × d − Exp(ω t_d)ᵀ R_kᵀ v_k: the body's turn and its motion over the offset
                seen_motion = np.cross(d, frame_rates(pr, est.b_g)[k]) - np.einsum("nab,ncb,nc->na", turn_t, R[k], est.v[k])
                out.J_td = A @ seen_motion[..., None]
            out.J_p = -out.J_f  # w.r.t. p_k (none for frame 0, the origin)
        # IMU increments between frames, then the bias priors: few rows, dense over the non-point unknowns.
        rows, dense = [], []
        dg = -pr.gravity * skew(est.g_dir) @ tangent  # ∂g/∂(tilt)
        for kk in range(K - 1):
            dt = pr.frame_t[kk + 1] - pr.frame_t[kk]
            dS = ints.S[:, kk + 1] - ints.S[:, kk] - ints.V[:, kk] * dt
            dM = ints.M[:, kk + 1] - ints.M[:, kk] - ints.MV[:, kk] * dt
            dV = ints.V[:, kk + 1] - ints.V[:, kk]
            dMV = ints.MV[:, kk + 1] - ints.MV[:, kk]
            imu_p = dS - dM @ est.b_a
            imu_v = dV - dMV @ est.b_a
            r_p = est.p[kk + 1] - est.p[kk] - est.v[kk] * dt - 0.5 * g * dt * dt - imu_p[0]
            r_v = est.v[kk + 1] - est.v[kk] - g * dt - imu_v[0]
            W = self.imu_sqrt_info[kk]
            rows.append(W @ np.concatenate([r_p, r_v]))
            if jacobian:
                Jk = np.zeros((6, n_c))
                Jk[0:3, lay.G] = -0.5 * dt * dt * dg
                Jk[3:6, lay.G] = -dt * dg
                Jk[0:3, lay.BG] = -((imu_p[1:] - imu_p[0]) / eps).T
                Jk[3:6, lay.BG] = -((imu_v[1:] - imu_v[0]) / eps).T
                Jk[0:3, lay.BA] = dM[0]
                Jk[3:6, lay.BA] = dMV[0]
                Jk[0:3, lay.p(kk + 1)] = np.eye(3)
                if kk >= 1:
                    Jk[0:3, lay.p(kk)] = -np.eye(3)
                Jk[0:3, lay.v(kk)] = -dt * np.eye(3)
                Jk[3:6, lay.v(kk + 1)] = np.eye(3)
                Jk[3:6, lay.v(kk)] = -np.eye(3)
                dense.append(W @ Jk)
        rows.append((est.b_g - pr.bias_g) / pr.sigma_bias_g)
        rows.append(est.b_a / pr.sigma_bias_a)
        if pr.solves_time_offset:
            rows.append(np.array([(est.t_d - pr.time_offset_prior) / pr.sigma_time_offset]))
        out.r_dense = np.concatenate(rows)
        if jacobian:
            Jb = np.zeros((6 + lay.time_offset, n_c))
            Jb[0:3, lay.BG] = np.eye(3) / pr.sigma_bias_g
            Jb[3:6, lay.BA] = np.eye(3) / pr.sigma_bias_a
            if pr.solves_time_offset:
                Jb[6, lay.TD] = 1.0 / pr.sigma_time_offset
            dense.append(Jb)
            out.J_dense = np.vstack(dense)
        return out

    def pixel_chi2(self, est: _Estimate) -> np.ndarray:
        """Whitened squared pixel residual of every observation (inlier or not)."""
        pr = self.problem
        R = _integrals(pr, est.b_g).R
        k, j = pr.obs_frame, pr.obs_point
        d = exposure_bodies(pr, est, R, k, j)[0]
        h = (d - pr.t_BC) @ pr.R_BC
        with np.errstate(divide="ignore", invalid="ignore"):
            z = h[:, 0:2] / h[:, 2:3]
            e = (z - pr.obs_xn) * (pr.focal_px / pr.pixel_sigma)
        chi2 = np.sum(e * e, axis=1)
        return np.where(h[:, 2] > 0.0, chi2, np.inf)


def solve_window(problem: WindowProblem, max_gravity_error: float = 0.1, iterations: int = 15,
                 outlier_chi2: float = 11.8, rescales: tuple[float, ...] = (0.6, 1.6)) -> WindowSolution:
    """The refined window, or :class:`WindowFailure` saying why it does not determine the start.

    The refinement starts from the linear guess and, because a weak window can hold a second
    minimum at another scale, also from that solution shrunk and stretched by ``rescales``; the
    lowest robust cost wins. Wrong tracks are down-weighted (Cauchy loss) and then dropped
    before the final, plain least squares that gives the covariance.
    """
    K, M = problem.n_frames, problem.n_points
    if K < 3 or M < 6:
        raise WindowFailure(f"{K} frames and {M} tracked points: too few", "tracks")
    b_g = problem.bias_g.copy()
    v0, g_lin, _ = linear_guess(problem, b_g)
    g_norm = float(np.linalg.norm(g_lin))
    if not (math.isfinite(g_norm) and abs(g_norm / problem.gravity - 1.0) <= max_gravity_error):
        raise WindowFailure(f"|g| {g_norm:.2f} m/s^2 from the linear guess: too little motion to fix the scale", "motion")
    v0, g_dir, baselines, b_a = scale_given_gravity(problem, g_lin, b_g)
    if np.sum(baselines < 0.0) > 0.25 * len(baselines):
        raise WindowFailure("the camera moves against the directions the images say", "motion")
    ints = _integrals(problem, b_g)
    tau = problem.frame_t
    p = np.outer(tau, v0) + 0.5 * np.outer(tau * tau, problem.gravity * g_dir) + ints.S - ints.M @ b_a
    v = v0 + np.outer(tau, problem.gravity * g_dir) + ints.V - ints.MV @ b_a
    model = _Residuals(problem, np.ones(len(problem.obs_frame), dtype=bool))
    first = _Estimate(g_dir, b_g.copy(), b_a, p - p[0], v, triangulate(problem, ints.R, p - p[0] + ints.R @ problem.t_BC),
                      problem.time_offset_prior if problem.solves_time_offset else 0.0)
    first, used = _refine(model, first, iterations, robust=2.0)
    fits = [(_robust(model, model.evaluate(first, tangent_basis(first.g_dir), False), 2.0)[0], first)]
    for factor in rescales:
        R = _integrals(problem, first.b_g).R
        other = _Estimate(first.g_dir, first.b_g.copy(), first.b_a.copy(), first.p * factor, first.v * factor,
                          triangulate(problem, R, first.p * factor + R @ problem.t_BC), first.t_d)
        other, more = _refine(model, other, iterations, robust=2.0)
        used += more
        fits.append((_robust(model, model.evaluate(other, tangent_basis(other.g_dir), False), 2.0)[0], other))
    cost, est = min(fits, key=lambda x: x[0])
    inliers = model.pixel_chi2(est) <= outlier_chi2
    counts = np.bincount(problem.obs_point[inliers], minlength=M)
    inliers &= counts[problem.obs_point] >= 2  # a point seen once says nothing, and would leave H singular
    counts = np.bincount(problem.obs_point[inliers], minlength=M)
    if np.sum(counts >= 2) < 6 or np.mean(inliers) < 0.5:
        raise WindowFailure("too few points consistent with the motion", "tracks")
    model = _Residuals(problem, inliers)
    est, more = _refine(model, est, iterations)
    used += more
    tangent = tangent_basis(est.g_dir)
    lin = model.evaluate(est, tangent)
    H_cc, H_cf, H_ff, _, _ = lin.normal_equations(np.ones(len(lin.frame)), Layout.of(problem))
    # Points left without observations are not in the solution: any pin keeps the inverse defined.
    H_ff[counts < 2] += np.eye(3)
    try:
        cov = _covariance(H_cc, H_cf, H_ff)
    except np.linalg.LinAlgError:
        raise WindowFailure("singular information matrix", "information") from None
    n_c = len(H_cc)
    if not np.all(np.isfinite(cov)) or np.linalg.eigvalsh(cov[:n_c, :n_c]).min() <= 0.0:
        raise WindowFailure("information matrix too ill-conditioned for a covariance", "information")
    r2 = float(np.sum(lin.r_pix**2) + lin.r_dense @ lin.r_dense)
    ratio = math.sqrt(r2 / max(2 * len(lin.frame) + len(lin.r_dense) - Layout.of(problem).size, 1))
    cov *= max(1.0, ratio**2)
    # Another start that fits about as well at a clearly different velocity: the scale is ambiguous.
    lay = Layout.of(problem)
    sigma_v = math.sqrt(max(float(np.trace(cov[lay.v(0), lay.v(0)])), 0.0))
    for other_cost, other in fits:
        if other_cost <= cost + 4.0 and np.linalg.norm(other.v[0] - est.v[0]) > 3.0 * sigma_v + 1e-3:
            raise WindowFailure("two scales fit the window about equally well", "scale")
    return WindowSolution(est.g_dir, est.b_g, est.b_a, est.p, est.v, _integrals(problem, est.b_g).R, est.f,
                          cov, tangent, ratio, g_norm, inliers, used, est.t_d)


def scale_sigma(problem: WindowProblem, solution: WindowSolution) -> float:
    """The relative sigma of the window's scale, from the window's own information.

    The scale is the common stretch ``s`` of the IMU's positions about frame 0 (the origin):
    ``p̂_k (1 + s)`` fits them best for ``s = Σ p̂_kᵀ δp_k / Σ |p̂_k|²``, a linear function of
    the position errors, so its variance is ``wᵀ P w`` over their covariance. A window that
    barely moves, or whose acceleration is drowned by the accelerometer's noise, leaves it
    large; a lively one makes it small whatever the excitation's RMS.
    """
    lay = Layout.of(problem)
    cols = slice(lay.p(1).start, lay.v(0).start)
    p = solution.p[1:].reshape(-1)
    norm = float(p @ p)
    if norm <= 0.0:
        return math.inf
    w = p / norm
    return math.sqrt(max(float(w @ solution.cov[cols, cols] @ w), 0.0))


def _robust(model: _Residuals, lin: _Linearised, robust: float | None) -> tuple[float, np.ndarray]:
    """Cost and per-observation weights: the pixel residuals under a Cauchy loss of scale ``robust``
    (a few wrong tracks must not pull the whole window), the IMU and the priors squared."""
    s = lin.chi2()
    dense = float(lin.r_dense @ lin.r_dense)
    if robust is None:
        return float(np.sum(s)) + dense, np.ones(len(s))
    c2 = robust * robust
    return float(np.sum(c2 * np.log1p(s / c2))) + dense, 1.0 / (1.0 + s / c2)


def _refine(model: _Residuals, est: _Estimate, iterations: int, robust: float | None = None) -> tuple[_Estimate, int]:
    """Levenberg–Marquardt from ``est`` (iteratively reweighted under a Cauchy loss when ``robust``)."""
    pr = model.problem
    lay = Layout.of(pr)
    lam = 1e-4
    used = 0
    for used in range(1, iterations + 1):
        tangent = tangent_basis(est.g_dir)
        lin = model.evaluate(est, tangent)
        cost, w = _robust(model, lin, robust)
        H_cc, H_cf, H_ff, g_c, g_f = lin.normal_equations(w, lay)
        improved = False
        for _ in range(6):
            try:
                dx = _solve_normal(H_cc, H_cf, H_ff, g_c, g_f, lam)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            cand = est.moved(dx, lay, tangent)
            new_cost = _robust(model, model.evaluate(cand, tangent_basis(cand.g_dir), jacobian=False), robust)[0]
            if math.isfinite(new_cost) and new_cost < cost:
                est, improved = cand, True
                lam = max(lam * 0.2, 1e-9)
                break
            lam *= 10.0
        if not improved or (cost - new_cost) < 1e-6 * cost:
            break
    return est, used
