"""A bank of heading hypotheses: the heading from GPS and IMU, from any motion, with an honest sigma.

Without a magnetometer the heading is unknown at start and only horizontal accelerations
show it, slowly when the motion is gentle. An EKF cannot start from "anywhere on the circle"
(its linearisation holds for a few tens of degrees at most), so the bank runs ``n`` copies of
the robot filter, each started with the same roll, pitch, position, velocity and biases but a
heading ``2πk/n`` apart, with a heading sigma of half the spacing: between them they cover
the circle. Every copy gets the same IMU steps and GPS fixes as an ordinary filter (heading
included: no held states), and is weighted by how well it predicted each fix (a Gaussian-sum
filter). The mixture's heading sigma — the spread of the hypotheses by weight plus their own
sigmas — is honest by construction; once it is below ``place_sigma_deg`` the best copy, with
that sigma, becomes the filter (:meth:`HeadingBank.placed`). A copy near the true heading
converges onto it, copies far from it fall behind in weight, so no heading is ever guessed.

While the vehicle stands still or flies straight at constant speed all hypotheses predict the
fixes equally well and the weights stay where they are: the heading stays unknown, as it is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vtolpose.estimator.core import covariance
from vtolpose.estimator.core.covariance import BA, BG, TH, V, YAW
from vtolpose.estimator.core.kalman import chi2_gate, ekf_update
from vtolpose.estimator.core.measurements import GpsFix
from vtolpose.estimator.core.rotation import quat_conj, quat_log, quat_mul, rotvec_quat, yaw_of
from vtolpose.estimator.core.state import FilterState, StateLayout, stacked
from vtolpose.estimator.core.update_kernel import NO_HELD
from vtolpose.estimator.gnss import gps_kernel
from vtolpose.estimator.gnss.gps_update import GpsUpdater, gps_sigmas, place_at_fix
from vtolpose.estimator.inertial.imu_delta import ImuDelta
from vtolpose.estimator.inertial.propagator import ImuPropagator

UNKNOWN_HEADING_VAR = math.pi**2 / 3.0  # a heading uniform on the circle: its variance about any guess
_LIKELIHOOD_PROBABILITY = 0.9999  # one wild fix costs a hypothesis no more than this χ² quantile


@dataclass(slots=True)
class HeadingBankOptions:
    hypotheses: int = 8  # headings tried at start, evenly spaced around the circle
    place_sigma_deg: float = 10.0  # the heading is placed once the mixture's sigma is below this

    def __post_init__(self) -> None:
        if not 3 <= self.hypotheses <= 36:
            raise ValueError(f"heading bank hypotheses must be within 3..36, got {self.hypotheses}")
        if not 0.0 < self.place_sigma_deg < 90.0:
            raise ValueError(f"heading bank place_sigma_deg must be within (0, 90), got {self.place_sigma_deg}")


def rotated_about_down(state: FilterState, angle: float) -> FilterState:
    """A robot-only copy of ``state`` with its world frame turned by ``angle`` about down.

    Position and velocity stay (they are tied to the GPS frame, not to the attitude); the
    attitude and the world-frame attitude error turn with the heading, and the heading error
    forgets what it was correlated with.
    """
    n = state.robot_dim
    out = FilterState(state.layout)
    out.t_ns = state.t_ns
    out.p, out.v = state.p.copy(), state.v.copy()
    out.b_g, out.b_a = state.b_g.copy(), state.b_a.copy()
    out.q = quat_mul(np.array(rotvec_quat(0.0, 0.0, angle)), state.q)
    c, s = math.cos(angle), math.sin(angle)
    turn = np.eye(n)
    turn[TH, TH] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    out.cov = turn @ state.cov[:n, :n] @ turn.T
    covariance.forget_yaw(out.cov)
    return out


def with_bias_states(state: FilterState, sigma_gyro_bias: np.ndarray, sigma_accel_bias: float) -> FilterState:
    """``state`` with gyro and accelerometer bias states (their priors uncorrelated), for a model that has none:
    the hypotheses then measure the biases in flight, and the fixed-bias model takes them when the heading
    is placed."""
    if state.layout.estimates_biases:
        return state
    out = FilterState(StateLayout("biases"))
    out.t_ns = state.t_ns
    out.p, out.v, out.q, out.b_g, out.b_a = state.p.copy(), state.v.copy(), state.q.copy(), state.b_g.copy(), state.b_a.copy()
    n = state.robot_dim
    out.cov[:n, :n] = state.cov[:n, :n]
    out.cov[BG, BG] = np.diag(np.broadcast_to(np.asarray(sigma_gyro_bias, dtype=float) ** 2, (3,)))
    out.cov[BA, BA] = np.eye(3) * sigma_accel_bias**2
    return out


def circular_spread(headings: np.ndarray, weights: np.ndarray, variances: np.ndarray) -> tuple[float, float]:
    """Weighted mean heading of a Gaussian mixture on the circle and its variance about that mean."""
    mean = math.atan2(float(weights @ np.sin(headings)), float(weights @ np.cos(headings)))
    offset = np.angle(np.exp(1j * (headings - mean)))
    return mean, float(weights @ (variances + offset**2))


class HeadingBank:
    """``n`` robot filters a heading apart, weighted by their GPS likelihood (see the module docstring)."""

    def __init__(self, options: HeadingBankOptions, start: FilterState, propagator: ImuPropagator, gps: GpsUpdater,
                 velocity_sigma: float | None = None) -> None:
        """Hypotheses around ``start``; each takes its position from the first fix it gets.
        ``velocity_sigma``: forget ``start``'s velocity covariance for this (not smaller) sigma."""
        self.options = options
        self.propagator = propagator
        self.gps = gps
        n = options.hypotheses
        spacing = 2.0 * math.pi / n
        self.members = [rotated_about_down(start, k * spacing) for k in range(n)]
        for member in self.members:
            member.cov[YAW, YAW] = (0.5 * spacing) ** 2
            if velocity_sigma is not None:
                var = np.maximum(covariance.block_variances(member.cov, V), velocity_sigma**2)
                covariance.reinitialise(member.cov, V, np.diag(var))
        self.log_weights = np.full(n, -math.log(n))
        self.positioned = False
        self.fixes = 0
        self._likelihood_cap = chi2_gate(3, _LIKELIHOOD_PROBABILITY)

    @property
    def weights(self) -> np.ndarray:
        return np.exp(self.log_weights)

    def propagate(self, delta: ImuDelta) -> None:
        if not self.propagator.propagate_all(self.members, delta):
            for member in self.members:
                self.propagator.propagate(member, delta)
        for member in self.members:
            member.t_ns = delta.t1_ns

    def propagate_run(self, deltas: np.ndarray, dts: np.ndarray, t_ns: int) -> bool:
        """:meth:`propagate` over each of a sequence of deltas ([Δθ, Δv] rows; the last ending at ``t_ns``) in
        one compiled call; False, with nothing done, where the propagator declines it."""
        if not self.propagator.propagate_all_run(self.members, deltas, dts):
            return False
        for member in self.members:
            member.t_ns = t_ns
        return True

    def update(self, fix: GpsFix) -> None:
        """Fuse one fix into every hypothesis and reweight them by how well each predicted it."""
        if not self.positioned:
            for member in self.members:
                place_at_fix(member, fix, self.gps.model.lever_arm_b, self.gps.sigma_floor_m)
            self.positioned = True
            return
        sigma_h, sigma_v = gps_sigmas(fix, self.gps.sigma_floor_m)
        parts = stacked(self.members)
        gate = self.gps.gate
        # Every hypothesis' update in one compiled call, its correction folded in.
        info, _ = gps_kernel.gps_update(
            *parts, True, self.members[0].layout.estimates_biases, self.gps.model.lever_arm_b,
            np.ascontiguousarray(fix.p_ned, dtype=float), sigma_h**2, sigma_v**2, math.inf if gate is None else float(gate),
            NO_HELD)
        for member, *rows in zip(self.members, *parts):
            member.p, member.v, member.q, member.b_g, member.b_a, member.cov = rows
        # A broken hypothesis (not accepted, not finite) is out of the race.
        usable = info[:, 3] > 0.0
        log_like = np.full(len(self.members), -np.inf)
        log_like[usable] = -0.5 * (np.minimum(info[usable, 1], self._likelihood_cap) + info[usable, 2])
        if not np.any(np.isfinite(log_like)):
            return
        w = self.log_weights + log_like
        self.log_weights = w - _logsumexp(w)
        self.fixes += 1

    def at_rest(self, gyro_mean: np.ndarray, gyro_var: np.ndarray, zupt_sigma: float) -> None:
        """A still chunk (``inertial/stillness``): zero velocity and the gyro bias, in every hypothesis
        alike (neither says anything about the heading, so the weights stay)."""
        for member in self.members:
            ekf_update(member, slice(3, 6), np.eye(3), -member.v, np.eye(3) * zupt_sigma**2)
            ekf_update(member, slice(9, 12), np.eye(3), gyro_mean - member.b_g, np.diag(gyro_var))

    def heading(self) -> tuple[float, float]:
        """The mixture's heading [rad] and its sigma [rad] (its spread by weight plus each hypothesis' own)."""
        _, _, _, mean, var = self._mixture()
        return mean, math.sqrt(var)

    def placed(self) -> FilterState | None:
        """The best hypothesis once the mixture's sigma is below ``place_sigma_deg``, with the mixture's
        covariance about *it*: ``Σ w_i (P_i + d_i d_iᵀ)``, ``d_i`` hypothesis i's state less the chosen one's.

        The others' weight still counts against its heading, and with it against everything a heading drags
        along: a hypothesis a few degrees off has flown the same fixes with its own tilt, velocity and biases
        (in a turn a heading error is a sideways acceleration, taken up by the tilt), so the spread is
        correlated across them. Only the heading's share of it (the diagonal) left the tilt claimed to a
        third of a degree while it stayed 0.7° off after the landfill's start in flight."""
        _, weights, _, _, var = self._mixture()
        if math.sqrt(var) > math.radians(self.options.place_sigma_deg):
            return None
        k = int(np.argmax(self.log_weights))
        chosen = self.members[k]
        state = chosen.copy()
        n = state.robot_dim
        cov = np.zeros((n, n))
        for w, member in zip(weights, self.members):
            d = np.zeros(n)
            d[0:3] = member.p - chosen.p
            d[V] = member.v - chosen.v
            d[TH] = quat_log(quat_mul(member.q, quat_conj(chosen.q)))
            if state.layout.estimates_biases:
                d[BG] = member.b_g - chosen.b_g
                d[BA] = member.b_a - chosen.b_a
            cov += w * (member.cov[:n, :n] + np.outer(d, d))
        state.cov[:n, :n] = 0.5 * (cov + cov.T)
        return state

    def _mixture(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        """Each hypothesis' heading, weight and heading variance, and the mixture's mean heading and variance."""
        headings = yaw_of(np.array([m.q for m in self.members]))
        weights, variances = self.weights, np.array([m.cov[YAW, YAW] for m in self.members])
        return headings, weights, variances, *circular_spread(headings, weights, variances)


def _logsumexp(x: np.ndarray) -> float:
    top = float(np.max(x))
    return top + math.log(float(np.sum(np.exp(x - top))))
