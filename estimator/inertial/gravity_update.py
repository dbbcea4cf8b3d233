"""Levelling with the accelerometer as a gravity reference, used before the heading is known.

While the heading is unknown GPS cannot correct roll and pitch (a horizontal acceleration
error could be tilt or heading), yet a gyro bias tilts the attitude within seconds. The mean
specific force over a short interval is ``f ≈ -R^T g_W + b_a`` when the vehicle is not
accelerating much, and it says nothing about heading: the yaw column of its Jacobian is
exactly zero. The noise is inflated by how far |f| is from g, so manoeuvres count for little.
"""

from __future__ import annotations

import numpy as np

from vtolpose.estimator.core.kalman import UpdateOutcome, ekf_update
from vtolpose.estimator.core.rotation import skew
from vtolpose.estimator.core.state import FilterState


_THETA_BA = np.r_[6:9, 12:15]  # the columns of [δθ, δb_a] (made once: np.r_ costs more than the update's arithmetic)
_THETA = np.arange(6, 9)


class GravityModel:
    """``h(x) = -R^T g_W + b_a`` and its Jacobian over [δθ, δb_a] (global attitude error)."""

    def __init__(self, gravity: float) -> None:
        self.g_w = np.array([0.0, 0.0, float(gravity)])

    def predict(self, state: FilterState) -> np.ndarray:
        return -state.R.T @ self.g_w + (state.b_a if state.layout.estimates_biases else 0.0)

    def jacobian(self, state: FilterState) -> tuple[np.ndarray, np.ndarray]:
        """Columns and H: ``∂h/∂δθ = -R^T [g_W]×``, ``∂h/∂δb_a = I``."""
        H_theta = -state.R.T @ skew(self.g_w)
        if state.layout.estimates_biases:
            return _THETA_BA, np.hstack([H_theta, np.eye(3)])
        return _THETA, H_theta


class GravityLeveller:
    def __init__(self, gravity: float, base_sigma: float, gate: float | None) -> None:
        self.model = GravityModel(gravity)
        self.base_sigma = base_sigma
        self.gate = gate

    def update(self, state: FilterState, f_mean: np.ndarray, held: np.ndarray | None) -> UpdateOutcome:
        excess = abs(float(np.linalg.norm(f_mean)) - self.model.g_w[2])
        sigma = self.base_sigma + 2.0 * excess
        cols, H = self.model.jacobian(state)
        return ekf_update(state, cols, H, f_mean - self.model.predict(state), np.eye(3) * sigma**2, self.gate, held)
