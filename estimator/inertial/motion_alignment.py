"""In-motion alignment: attitude (heading included) and IMU biases from GPS and IMU windows.

A batch fit over a window, which the GPS calibrations (time offset, lever arm:
``vtolpose.estimator.calibration.gps``) solve for many windows; the filter itself finds its
heading with the bank of hypotheses (``heading_bank``), whose sigma carries the IMU's noise,
which this fit's does not. GPS positions pin the attitude down once the vehicle accelerates:
over a window starting at ``t0``

    p(t) = p0 + v0 τ + ½ g_W τ² + R0 [ S(τ; b_g) − M(τ; b_g) b_a + ΔR(τ; b_g) l ]

with ``ΔR`` the gyro-integrated rotation since ``t0``, ``S`` the double integral of the
rotated specific force, ``M`` that of the rotation alone, and ``l`` the antenna lever arm.
A linear fit with an unconstrained 3 × 3 in place of ``R0`` gives a first guess;
damped Gauss–Newton refines ``[p0, v0, R0, b_g, b_a]`` (trying the other three quarter-turn
headings if the first start converges badly). A solution is offered only when its attitude
is well determined and its residuals match the GPS noise.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from vtolpose.estimator.inertial.imu_delta import ImuDelta
from vtolpose.estimator.core.covariance import BA, P, TH, V
from vtolpose.estimator.core.rotation import rot_to_quat, skew, so3_exp

ATTITUDE_AND_BIASES = slice(TH.start, BA.stop)  # δθ, δb_g, δb_a: the fit's last nine parameters, in the state's order


@dataclass(slots=True)
class MotionAlignOptions:
    window_s: float = 10.0
    min_window_s: float = 4.0
    solve_every_s: float = 1.0
    max_sigma_tilt_deg: float = 1.5
    max_sigma_heading_deg: float = 2.0
    max_residual_ratio: float = 3.0  # RMS normalised residual above which the model is not believed
    iterations: int = 25


@dataclass(frozen=True, slots=True)
class MotionAlignment:
    """The state at the last IMU sample of the window, with its uncertainty."""

    t_ns: int
    q: np.ndarray
    p: np.ndarray  # IMU position, world
    v: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    cov: np.ndarray  # 15 × 15 over [δp, δv, δθ, δb_g, δb_a]
    residual_ratio: float
    window_s: float
    n_fixes: int


@dataclass(slots=True)
class _Integrals:
    R: np.ndarray  # (K, 3, 3) ΔR at each query time
    S: np.ndarray  # (K, 3)
    M: np.ndarray  # (K, 3, 3)
    V: np.ndarray  # (K, 3)
    MV: np.ndarray  # (K, 3, 3)


def _prefix_products(d: np.ndarray) -> np.ndarray:
    """``[I, d0, d0 d1, d0 d1 d2, …]`` for a stack ``(..., n, 3, 3)``, in log2(n) batched steps."""
    out = np.concatenate([np.broadcast_to(np.eye(3), d.shape[:-3] + (1, 3, 3)), d], axis=-3).copy()
    shift = 1
    n = out.shape[-3]
    while shift < n:
        out[..., shift:, :, :] = out[..., :-shift, :, :] @ out[..., shift:, :, :]
        shift *= 2
    return out


def integrate(
    t: np.ndarray, dtheta: np.ndarray, dvel: np.ndarray, b_g: np.ndarray, query_t: np.ndarray
) -> _Integrals:
    """Strapdown integrals of IMU deltas from ``t[0]`` at ``query_t`` (seconds).

    ``t`` holds the n + 1 step boundaries, ``dtheta``/``dvel`` the n raw deltas. ``b_g`` is one
    gyro bias ``(3,)`` or a batch ``(B, 3)`` (outputs then lead with B). The bias correction is
    the propagator's, so the fit and the filter integrate identically.
    """
    dt = np.diff(t)
    phi = dtheta - b_g[..., None, :] * dt[:, None]
    dv = dvel - 0.5 * dt[:, None] * np.cross(b_g[..., None, :], dvel)
    R = _prefix_products(so3_exp(phi))
    R_start = R[..., :-1, :, :]
    inc = np.einsum("...nij,...nj->...ni", R_start, dv)  # velocity increments in the t0 frame
    zero_v = np.zeros(inc.shape[:-2] + (1, 3))
    zero_m = np.zeros(R_start.shape[:-3] + (1, 3, 3))
    V = np.concatenate([zero_v, np.cumsum(inc, axis=-2)], axis=-2)
    S = np.concatenate([zero_v, np.cumsum(V[..., :-1, :] * dt[:, None] + 0.5 * inc * dt[:, None], axis=-2)], axis=-2)
    MV = np.concatenate([zero_m, np.cumsum(R_start * dt[:, None, None], axis=-3)], axis=-3)
    M = np.concatenate(
        [zero_m, np.cumsum(MV[..., :-1, :, :] * dt[:, None, None] + 0.5 * R_start * (dt**2)[:, None, None], axis=-3)],
        axis=-3,
    )
    # A query between boundaries: extrapolate from the boundary just before it (≤ one step).
    k = np.clip(np.searchsorted(t, query_t, side="right") - 1, 0, len(t) - 1)
    d = (query_t - t[k])[:, None]
    Vk, MVk = V[..., k, :], MV[..., k, :, :]
    return _Integrals(R[..., k, :, :], S[..., k, :] + Vk * d, M[..., k, :, :] + MVk * d[:, :, None], Vk, MVk)


class MotionAligner:
    """Buffers IMU samples and GPS fixes; offers an alignment once the window supports one."""

    def __init__(self, options: MotionAlignOptions, gravity: float, lever_arm_b: np.ndarray) -> None:
        self.options = options
        self.g_w = np.array([0.0, 0.0, float(gravity)])
        self.lever = np.asarray(lever_arm_b, dtype=float)
        self._deltas: deque[ImuDelta] = deque()
        self._fixes: deque[tuple[int, np.ndarray, float, float]] = deque()
        self._last_solve_t: int | None = None
        self.prior_bias = (np.zeros(3), 0.1, np.zeros(3), 0.2)  # b_g, σ [rad/s]; b_a, σ [m/s²]
        # Biases of the previous window: the next, overlapping window starts from them, which
        # turns a dozen Gauss–Newton iterations from zero into two or three.
        self._warm: tuple[np.ndarray, np.ndarray] | None = None
        self.last_failure = ""

    def set_bias_prior(self, b_g: np.ndarray, sigma_g: float, b_a: np.ndarray, sigma_a: float) -> None:
        """What the filter already knows of the biases (e.g. from a still start)."""
        self.prior_bias = (np.asarray(b_g, float).copy(), float(sigma_g), np.asarray(b_a, float).copy(), float(sigma_a))
        self._warm = None

    def add_delta(self, delta: ImuDelta) -> None:
        """Add the next IMU delta (contiguous with the previous one)."""
        if self._deltas and delta.t0_ns != self._deltas[-1].t1_ns:
            self._deltas.clear()  # a gap in the IMU: start the window again
            self._fixes.clear()
        self._deltas.append(delta)
        horizon = int((self.options.window_s + 1.0) * 1e9)
        while len(self._deltas) > 2 and delta.t1_ns - self._deltas[0].t0_ns > horizon:
            self._deltas.popleft()

    def add_fix(self, t_ns: int, p: np.ndarray, sigma_h: float, sigma_v: float) -> MotionAlignment | None:
        opts = self.options
        if not self._deltas or t_ns < self._deltas[0].t0_ns:
            return None  # the integrals are unknown before the first IMU delta
        self._fixes.append((t_ns, np.asarray(p, dtype=float), sigma_h, sigma_v))
        start = self._deltas[0].t0_ns
        while self._fixes and (t_ns - self._fixes[0][0] > int(opts.window_s * 1e9) or self._fixes[0][0] < start):
            self._fixes.popleft()
        span = (t_ns - self._fixes[0][0]) * 1e-9
        if span < opts.min_window_s or len(self._fixes) < 10 or len(self._deltas) < 10:
            return None
        if self._last_solve_t is not None and (t_ns - self._last_solve_t) * 1e-9 < opts.solve_every_s:
            return None
        self._last_solve_t = t_ns
        return self._solve(span)

    # ------------------------------------------------------------------------------ fitting
    def _model(self, ints: _Integrals, b_a: np.ndarray) -> np.ndarray:
        return ints.S - ints.M @ b_a + ints.R @ self.lever

    def _fit(self, data, R0: np.ndarray):
        """Damped Gauss–Newton from ``R0``; returns (cost, x, R0, J, residual) or None."""
        imu_t, dtheta, dvel, fix_t, fix_p, sig = data
        bg0, sbg, ba0, sba = self.prior_bias
        b_g, b_a = self._start_biases()
        p0 = fix_p[0].copy()
        v0 = np.zeros(3)
        K = len(fix_t)
        eps = 1e-5
        lam = 1e-3

        def evaluate(p0, v0, R0, b_g, b_a):
            ints = integrate(imu_t, dtheta, dvel, b_g, fix_t)
            body = self._model(ints, b_a)
            pred = p0 + np.outer(fix_t, v0) + 0.5 * np.outer(fix_t**2, self.g_w) + body @ R0.T
            res = np.concatenate([((fix_p - pred) / sig).reshape(-1), (bg0 - b_g) / sbg, (ba0 - b_a) / sba])
            return ints, body, res

        ints, body, res = evaluate(p0, v0, R0, b_g, b_a)
        # p0 and v0 enter linearly: start them at their best values for this R0.
        for _ in range(self.options.iterations):
            J = np.zeros((3 * K + 6, 15))
            eye = np.broadcast_to(np.eye(3), (K, 3, 3))
            Jr = np.zeros((K, 3, 15))
            Jr[:, :, 0:3] = eye
            Jr[:, :, 3:6] = eye * fix_t[:, None, None]
            Jr[:, :, 6:9] = -skew(body @ R0.T)
            Jr[:, :, 12:15] = -np.einsum("ij,kjl->kil", R0, ints.M)
            alt = integrate(imu_t, dtheta, dvel, b_g + eps * np.eye(3), fix_t)
            for j in range(3):
                alt_body = alt.S[j] - alt.M[j] @ b_a + alt.R[j] @ self.lever
                Jr[:, :, 9 + j] = (alt_body - body) @ R0.T / eps
            J[: 3 * K] = (Jr / sig.reshape(K, 3)[:, :, None]).reshape(3 * K, 15)
            J[3 * K : 3 * K + 3, 9:12] = np.eye(3) / sbg
            J[3 * K + 3 :, 12:15] = np.eye(3) / sba
            cost = float(res @ res)
            normal = J.T @ J
            grad = J.T @ res
            improved = False
            for _ in range(8):
                dx = np.linalg.solve(normal + lam * np.diag(np.diag(normal) + 1e-12), grad)
                cand = (p0 + dx[0:3], v0 + dx[3:6], so3_exp(dx[6:9]) @ R0, b_g + dx[9:12], b_a + dx[12:15])
                c_ints, c_body, c_res = evaluate(*cand)
                c_cost = float(c_res @ c_res)
                if c_cost < cost:
                    p0, v0, R0, b_g, b_a = cand
                    ints, body, res = c_ints, c_body, c_res
                    lam = max(lam / 10.0, 1e-7)
                    improved = True
                    break
                lam *= 10.0
            if not improved or c_cost > cost * (1.0 - 1e-6):
                break
        return float(res @ res), (p0, v0, R0, b_g, b_a), J, res

    def _start_biases(self) -> tuple[np.ndarray, np.ndarray]:
        if self._warm is not None:
            return self._warm[0].copy(), self._warm[1].copy()
        return self.prior_bias[0].copy(), self.prior_bias[2].copy()

    def _first_guess(self, data) -> np.ndarray:
        """Roll and pitch from the window's mean specific force (gravity, once the vehicle's own
        accelerations average out), heading from a linear fit with an unconstrained 3 × 3."""
        imu_t, dtheta, dvel, fix_t, fix_p, sig = data
        b_g, b_a = self._start_biases()
        along = integrate(imu_t, dtheta, dvel, b_g, imu_t[:-1])
        dt = np.diff(imu_t)
        f0 = np.sum(np.einsum("nij,nj->ni", along.R, dvel - np.outer(dt, b_a)), axis=0) / (imu_t[-1] - imu_t[0])
        down = -f0 / np.linalg.norm(f0)  # world down in the t0 body frame
        # R_tilt: the rotation taking the body vector ``down`` onto world down, with no heading.
        axis = np.cross(down, [0.0, 0.0, 1.0])
        angle = math.atan2(np.linalg.norm(axis), down[2])
        R_tilt = so3_exp(axis / np.linalg.norm(axis) * angle) if np.linalg.norm(axis) > 1e-12 else np.eye(3)
        K = len(fix_t)
        ints = integrate(imu_t, dtheta, dvel, b_g, fix_t)
        body = self._model(ints, b_a) @ R_tilt.T  # levelled, heading still unknown
        # p = p0 + v0 τ + ½ g τ² + Rz(ψ) body: linear in [p0, v0, cos ψ, sin ψ] (horizontal rows).
        rows = np.zeros((2 * K, 6))
        rows[0::2, 0], rows[1::2, 1] = 1.0, 1.0
        rows[0::2, 2], rows[1::2, 3] = fix_t, fix_t
        rows[0::2, 4], rows[0::2, 5] = body[:, 0], -body[:, 1]
        rows[1::2, 4], rows[1::2, 5] = body[:, 1], body[:, 0]
        w = 1.0 / sig[:, :2].reshape(-1)
        sol, *_ = np.linalg.lstsq(rows * w[:, None], fix_p[:, :2].reshape(-1) * w, rcond=None)
        heading = math.atan2(sol[5], sol[4])
        return so3_exp(np.array([0.0, 0.0, heading])) @ R_tilt

    def _solve(self, span: float) -> MotionAlignment | None:
        opts = self.options
        t0 = self._fixes[0][0]
        deltas = [d for d in self._deltas if d.t1_ns > t0]
        imu_t = np.array([(deltas[0].t0_ns - t0) * 1e-9] + [(d.t1_ns - t0) * 1e-9 for d in deltas])
        dtheta = np.array([d.dtheta for d in deltas])
        dvel = np.array([d.dvel for d in deltas])
        fix_t = np.array([(f[0] - t0) * 1e-9 for f in self._fixes])
        fix_p = np.array([f[1] for f in self._fixes])
        sig = np.array([[f[2], f[2], f[3]] for f in self._fixes])
        data = (imu_t, dtheta, dvel, fix_t, fix_p, sig)
        K = len(fix_t)
        R_start = self._first_guess(data)
        best = None
        for quarter in range(4):
            start = so3_exp(np.array([0.0, 0.0, quarter * math.pi / 2])) @ R_start
            fit = self._fit(data, start)
            if best is None or fit[0] < best[0]:
                best = fit
            if math.sqrt(best[0] / (3 * K)) <= opts.max_residual_ratio:
                break
        cost, (p0, v0, R0, b_g, b_a), J, res = best
        ratio = math.sqrt(float(np.mean(res[: 3 * K] ** 2)))
        if ratio < 2.0 * opts.max_residual_ratio:
            self._warm = (b_g.copy(), b_a.copy())
        try:
            cov = np.linalg.inv(J.T @ J)
        except np.linalg.LinAlgError:
            self.last_failure = "singular normal equations"
            return None
        sigma_theta = np.sqrt(np.maximum(np.diag(cov)[TH], 0.0)) * max(1.0, ratio)
        if ratio > opts.max_residual_ratio:
            self.last_failure = f"residuals {ratio:.1f}x the GPS noise"
            return None
        if max(sigma_theta[0], sigma_theta[1]) > math.radians(opts.max_sigma_tilt_deg):
            self.last_failure = f"tilt sigma {math.degrees(max(sigma_theta[:2])):.2f} deg"
            return None
        if sigma_theta[2] > math.radians(opts.max_sigma_heading_deg):
            self.last_failure = f"heading sigma {math.degrees(sigma_theta[2]):.2f} deg (too little horizontal acceleration)"
            return None
        # The fitted model at the last IMU sample: the filter starts there.
        t_end = imu_t[-1]
        end = integrate(imu_t, dtheta, dvel, b_g, np.array([t_end]))
        R_end = R0 @ end.R[0]
        v_end = v0 + self.g_w * t_end + R0 @ (end.V[0] - end.MV[0] @ b_a)
        p_end = p0 + v0 * t_end + 0.5 * self.g_w * t_end**2 + R0 @ (end.S[0] - end.M[0] @ b_a)
        out = np.zeros((BA.stop, BA.stop))
        out[P, P] = np.diag(sig[-1] ** 2)
        out[V, V] = cov[V, V] * max(1.0, ratio**2) + np.eye(3) * 0.02**2
        # A fit worse than the GPS noise is less certain than its normal equations say.
        out[ATTITUDE_AND_BIASES, ATTITUDE_AND_BIASES] = cov[ATTITUDE_AND_BIASES, ATTITUDE_AND_BIASES] * max(1.0, ratio**2)
        self.last_failure = ""
        return MotionAlignment(
            t_ns=deltas[-1].t1_ns,
            q=rot_to_quat(R_end),
            p=p_end,
            v=v_end,
            gyro_bias=b_g,
            accel_bias=b_a,
            cov=out,
            residual_ratio=ratio,
            window_s=span,
            n_fixes=K,
        )
