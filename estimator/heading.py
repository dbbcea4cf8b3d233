"""Initial heading from GPS once the vehicle accelerates (there is no magnetometer).

Until the heading is known the filter integrates the IMU in a level frame whose yaw is
arbitrary. In that frame the horizontal double integral ``S(t)`` of the specific force is the
true one rotated by the unknown heading error ψ, so at each GPS fix

    p_h(t) = p0 + v0 t + Rz(ψ) S(t)

which is linear in ``[p0, v0, cos ψ, sin ψ]``. A weighted least-squares fit over a sliding
window gives ψ, its standard deviation, and a scale ``hypot(cos, sin)`` that must be close to
one when the fit is meaningful. Motion with changing acceleration makes ψ observable; steady
flight or rest does not, and then the fit simply stays uncertain and is not accepted.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np


@dataclass(slots=True)
class AlignOptions:
    window_s: float = 10.0
    min_window_s: float = 3.0
    max_sigma_deg: float = 2.0
    max_scale_error: float = 0.15
    unaligned_accel_noise: float = 3.0  # m/s²/√Hz added to horizontal velocity before alignment


@dataclass(frozen=True, slots=True)
class HeadingSolution:
    yaw_correction: float  # rad, rotation about world down to apply to the filter's attitude
    sigma: float  # rad
    scale: float
    velocity_h: np.ndarray  # horizontal velocity at the last fix, in the aligned frame
    sigma_velocity: float
    n_fixes: int
    window_s: float


class HeadingAligner:
    def __init__(self, options: AlignOptions) -> None:
        self.options = options
        self._s = np.zeros(2)  # ∫∫ horizontal specific-force acceleration
        self._v = np.zeros(2)  # ∫ of the same
        self._fixes: deque[tuple[float, np.ndarray, float, np.ndarray, np.ndarray]] = deque()
        self._t = 0.0
        self.last: HeadingSolution | None = None

    def on_imu(self, dt: float, accel_w_horizontal: np.ndarray) -> None:
        """Accumulate the filter's world-frame (unaligned) horizontal acceleration over ``dt``."""
        self._s += self._v * dt + 0.5 * dt * dt * accel_w_horizontal
        self._v += accel_w_horizontal * dt
        self._t += dt

    def add_fix(self, p_h: np.ndarray, sigma_h: float) -> HeadingSolution | None:
        """Add a GPS fix (horizontal antenna position) at the current IMU time; return an accepted solution."""
        opts = self.options
        self._fixes.append((self._t, np.array(p_h, dtype=float), max(sigma_h, 1e-3), self._s.copy(), self._v.copy()))
        while self._fixes and self._t - self._fixes[0][0] > opts.window_s:
            self._fixes.popleft()
        span = self._t - self._fixes[0][0]
        if span < opts.min_window_s or len(self._fixes) < 8:
            return None
        solution = self._solve(span)
        self.last = solution
        if solution is None:
            return None
        accepted = solution.sigma <= math.radians(opts.max_sigma_deg) and abs(solution.scale - 1.0) <= opts.max_scale_error
        return solution if accepted else None

    def _solve(self, span: float) -> HeadingSolution | None:
        t0 = self._fixes[0][0]
        rows, rhs, weights = [], [], []
        for t, p, sigma, s, _ in self._fixes:
            dt = t - t0
            rows.append([1.0, 0.0, dt, 0.0, s[0], -s[1]])
            rows.append([0.0, 1.0, 0.0, dt, s[1], s[0]])
            rhs.extend(p)
            weights.extend([1.0 / sigma, 1.0 / sigma])
        w = np.array(weights)
        A = np.array(rows) * w[:, None]
        b = np.array(rhs) * w
        normal = A.T @ A
        try:
            cov = np.linalg.inv(normal)
        except np.linalg.LinAlgError:
            return None
        x = cov @ (A.T @ b)
        dof = len(b) - 6
        chi2_per_dof = float(np.sum((A @ x - b) ** 2)) / max(dof, 1)
        # Residuals larger than the fixes' sigma mean the model is off (gyro drift, tilt):
        # widen the uncertainty rather than trust the nominal one.
        cov *= max(1.0, chi2_per_dof)
        c, s = x[4], x[5]
        scale = math.hypot(c, s)
        if not math.isfinite(scale) or scale < 1e-6:
            return None
        u = np.array([-s, c]) / scale
        sigma = math.sqrt(max(float(u @ cov[4:6, 4:6] @ u), 0.0)) / scale
        v_last = self._fixes[-1][4]
        # v(t) = v0 + M V(t) with M = [[c, -s], [s, c]] from the same fit.
        J = np.array([[0.0, 0.0, 1.0, 0.0, v_last[0], -v_last[1]], [0.0, 0.0, 0.0, 1.0, v_last[1], v_last[0]]])
        velocity_h = J @ x
        sigma_v = math.sqrt(max(float(np.trace(J @ cov @ J.T)) / 2.0, 0.0))
        return HeadingSolution(math.atan2(s, c), sigma, scale, velocity_h, sigma_v, len(self._fixes), span)
