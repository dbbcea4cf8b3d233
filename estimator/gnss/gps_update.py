"""GPS position update (thesis eq. 4.6) with the antenna lever arm and a χ² gate.

``y = p + R(q) l + e``, ``e ~ N(0, diag(σ_h², σ_h², σ_v²))``. The thesis sets σ_v² = 2 σ_h²;
a fix that carries its own σ_v (NMEA GST, MAVLink epv) uses it instead.
"""

from __future__ import annotations

import math

import numpy as np

from vtolpose.estimator.core import covariance
from vtolpose.estimator.core.kalman import (REASONS, UpdateOutcome, compiled_outcome, ekf_update,
                                            innovation_covariance, normalized_innovation)
from vtolpose.estimator.core.update_kernel import NO_HELD
from vtolpose.estimator.gnss import gps_kernel
from vtolpose.estimator.core.measurements import GpsFix
from vtolpose.estimator.core.rotation import skew
from vtolpose.estimator.core.state import FilterState

GPS_COLS = covariance.NAV  # δp, δv, δθ: the only error states a fix depends on


def gps_sigmas(fix: GpsFix, floor_m: float) -> tuple[float, float]:
    """Horizontal and vertical 1-sigma of a fix, with the thesis' σ_v = √2 σ_h as fallback."""
    sigma_h = max(float(fix.sigma_h), floor_m)
    sigma_v = float(fix.sigma_v) if fix.sigma_v and math.isfinite(fix.sigma_v) and fix.sigma_v > 0 else math.sqrt(2.0) * sigma_h
    return sigma_h, max(sigma_v, floor_m)


def place_at_fix(state: FilterState, fix: GpsFix, lever_arm_b: np.ndarray, sigma_floor_m: float) -> None:
    """Position from a fix alone: the antenna at the fix, the IMU a lever arm away; position variance
    the fix's, uncorrelated with the rest (a first fix, or a re-initialisation)."""
    sigma_h, sigma_v = gps_sigmas(fix, sigma_floor_m)
    state.p = np.asarray(fix.p_ned, dtype=float) - state.R @ np.asarray(lever_arm_b, dtype=float)
    covariance.reinitialise(state.cov, covariance.P, np.diag([sigma_h**2, sigma_h**2, sigma_v**2]))


class GpsModel:
    """Measurement function and its analytic Jacobian (tested against central differences)."""

    def __init__(self, lever_arm_b: np.ndarray) -> None:
        self.lever_arm_b = np.asarray(lever_arm_b, dtype=float).reshape(3)
        self._position_block = np.hstack([np.eye(3), np.zeros((3, 6))])  # H's constant part

    def arm(self, state: FilterState) -> np.ndarray:
        """The lever arm in the world frame, ``R l`` (what both the prediction and the Jacobian use)."""
        return state.R @ self.lever_arm_b

    def predict(self, state: FilterState, arm: np.ndarray | None = None) -> np.ndarray:
        return state.p + (self.arm(state) if arm is None else arm)

    def jacobian(self, state: FilterState, arm: np.ndarray | None = None) -> np.ndarray:
        """∂y/∂[δp, δv, δθ] with the world-frame attitude error ``R_true = Exp(δθ) R``."""
        H = self._position_block.copy()
        H[:, 6:9] = -skew(self.arm(state) if arm is None else arm)
        return H


class GpsUpdater:
    def __init__(self, lever_arm_b: np.ndarray, gate: float | None, sigma_floor_m: float = 1e-3) -> None:
        self.model = GpsModel(lever_arm_b)
        self.gate = gate
        self.sigma_floor_m = sigma_floor_m

    def residual(self, state: FilterState, fix: GpsFix) -> np.ndarray:
        return np.asarray(fix.p_ned, dtype=float) - self.model.predict(state)

    def noise(self, fix: GpsFix) -> np.ndarray:
        sigma_h, sigma_v = gps_sigmas(fix, self.sigma_floor_m)
        return np.diag([sigma_h**2, sigma_h**2, sigma_v**2])

    def update(self, state: FilterState, fix: GpsFix, held: np.ndarray | None = None) -> UpdateOutcome:
        """Fuse ``fix``: in one compiled call (``gps_kernel``) where the covariance allows it, else through
        :func:`ekf_update` with the model's prediction and Jacobian (the same numbers either way)."""
        if not state.cov.flags.c_contiguous:
            return self.update_reference(state, fix, held)
        sigma_h, sigma_v = gps_sigmas(fix, self.sigma_floor_m)
        # A stack of one whose nominal rows are only read: without folding in, v, b_g and b_a are not
        # touched, so p stands in for them.
        p = np.ascontiguousarray(state.p, dtype=float).reshape(1, 3)
        info, dxs = gps_kernel.gps_update(
            p, p, np.ascontiguousarray(state.q, dtype=float).reshape(1, 4), p, p, state.cov[np.newaxis], False, False,
            self.model.lever_arm_b, np.ascontiguousarray(fix.p_ned, dtype=float), sigma_h**2, sigma_v**2,
            math.inf if self.gate is None else float(self.gate),
            NO_HELD if held is None else np.ascontiguousarray(held, dtype=np.bool_))
        code, nis = info[0, :2].tolist()
        return compiled_outcome(state, int(code), nis, dxs[0], 3)

    def update_filter(self, state: FilterState, fix: GpsFix,
                      claimed: tuple[float, float] | None) -> tuple[UpdateOutcome, np.ndarray]:
        """The filter's fix where its state has only the robot (IMU+GPS; C-ordered covariance, no map, no
        calibration states): :meth:`update`, the noise check's innovation and NIS under the ``claimed`` sigmas
        (None: no check) and :meth:`residual` after the update, in one compiled call (``gps_kernel.filter_fix``:
        a dozen numpy calls on three-element arrays cost more than their arithmetic). Returns the outcome and
        the kernel's row (``gps_kernel.FIX_INFO``: the check's NIS, the innovation, the posterior residual)."""
        sigma_h, sigma_v = gps_sigmas(fix, self.sigma_floor_m)
        claim_h, claim_v = (1.0, 1.0) if claimed is None else claimed
        info, p, v, q, b_g, b_a = gps_kernel.filter_fix(
            state.p, state.v, state.q, state.b_g, state.b_a, state.cov, state.layout.estimates_biases,
            self.model.lever_arm_b, np.ascontiguousarray(fix.p_ned, dtype=float), sigma_h**2, sigma_v**2,
            math.inf if self.gate is None else float(self.gate), claimed is not None, claim_h**2, claim_v**2)
        code, nis = int(info[0]), float(info[1])
        if code:
            return UpdateOutcome(False, nis, 3, REASONS[code]), info
        state.p, state.v, state.q, state.b_g, state.b_a = p, v, q, b_g, b_a
        if state.observer is not None:
            state.observer.updated(state)
        return UpdateOutcome(True, nis, 3), info

    def update_reference(self, state: FilterState, fix: GpsFix, held: np.ndarray | None = None) -> UpdateOutcome:
        """:meth:`update` from the model's prediction and Jacobian through :func:`ekf_update`."""
        arm = self.model.arm(state)
        residual = np.asarray(fix.p_ned, dtype=float) - self.model.predict(state, arm)
        return ekf_update(state, GPS_COLS, self.model.jacobian(state, arm), residual, self.noise(fix), self.gate, held)

    def update_heading_unknown(self, state: FilterState, fix: GpsFix, held_horizontal: np.ndarray) -> UpdateOutcome:
        """While the filter's frame has an arbitrary yaw: gated on all three axes, then the height fused
        into everything (its relation to tilt and biases does not depend on the heading) and the
        horizontal position into what ``held_horizontal`` leaves free (there it does)."""
        arm = self.model.arm(state)
        H, R = self.model.jacobian(state, arm), self.noise(fix)
        residual = np.asarray(fix.p_ned, dtype=float) - self.model.predict(state, arm)
        nis = normalized_innovation(innovation_covariance(state, GPS_COLS, H, R), residual)
        if nis is None or not np.all(np.isfinite(residual)):
            return UpdateOutcome(False, float("nan"), 3, "singular innovation covariance" if nis is None else "non-finite residual")
        if self.gate is not None and nis > self.gate:
            return UpdateOutcome(False, nis, 3, "chi2 gate")
        ekf_update(state, GPS_COLS, H[2:], residual[2:], R[2:, 2:])
        horizontal = self.residual(state, fix)[:2]
        ekf_update(state, GPS_COLS, self.model.jacobian(state)[:2], horizontal, R[:2, :2], None, held_horizontal)
        return UpdateOutcome(True, nis, 3)
