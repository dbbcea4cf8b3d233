"""GPS error model: antenna position plus Gaussian error with the thesis' σ_z² = 2 σ_xy².

The thesis (eq. 4.6–4.7) simulated GPS by adding white noise to the true position, with the
vertical variance doubled because height is the hardest coordinate for a receiver. Real
receivers' errors are also correlated over tens of seconds (multipath, atmosphere); the
optional first-order Gauss–Markov mode keeps the same per-fix σ but correlates successive
errors with time constant ``correlation_time_s``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class GpsErrorModel:
    """Rate, horizontal 1-σ [m], antenna lever arm in body FRD [m], optional correlation time."""

    sigma_h: float
    rate_hz: float = 10.0
    lever_arm_b: tuple[float, float, float] = (0.0, 0.0, 0.0)
    correlation_time_s: float | None = None

    def __post_init__(self) -> None:
        if not (np.isfinite(self.sigma_h) and self.sigma_h >= 0.0):
            raise ValueError(f"gps sigma_h must be finite and non-negative, got {self.sigma_h}")
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0.0):
            raise ValueError(f"gps rate_hz must be positive, got {self.rate_hz}")
        if len(self.lever_arm_b) != 3 or not np.all(np.isfinite(self.lever_arm_b)):
            raise ValueError(f"gps lever_arm_b must be 3 finite numbers, got {self.lever_arm_b}")
        tau = self.correlation_time_s
        if tau is not None and not (np.isfinite(tau) and tau > 0.0):
            raise ValueError(f"gps correlation_time_s must be positive or None, got {tau}")

    @property
    def sigma_v(self) -> float:
        """Vertical 1-σ: √2 σ_h (variance doubled, thesis eq. 4.7)."""
        return float(np.sqrt(2.0) * self.sigma_h)

    @property
    def sigmas(self) -> np.ndarray:
        return np.array([self.sigma_h, self.sigma_h, self.sigma_v])


def gps_errors(t_s: np.ndarray, model: GpsErrorModel, rng: np.random.Generator) -> np.ndarray:
    """Position errors (N, 3) in NED at times ``t_s``: white, or stationary Gauss–Markov."""
    n = len(t_s)
    draws = rng.standard_normal((n, 3)) * model.sigmas
    if model.correlation_time_s is None or n == 0:
        return draws
    # e_k = φ e_{k-1} + sqrt(1 - φ²) w_k keeps the variance σ² at every step; e_0 is stationary.
    phi = np.exp(-np.diff(np.asarray(t_s, dtype=float)) / model.correlation_time_s)
    errors = np.empty_like(draws)
    errors[0] = draws[0]
    for k in range(1, n):
        errors[k] = phi[k - 1] * errors[k - 1] + np.sqrt(1.0 - phi[k - 1] ** 2) * draws[k]
    return errors


def antenna_positions(p: np.ndarray, rotation: np.ndarray, model: GpsErrorModel) -> np.ndarray:
    """True antenna positions: ``p + R(q) l`` for each of N poses."""
    return p + rotation @ np.asarray(model.lever_arm_b, dtype=float)
