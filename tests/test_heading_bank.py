"""The heading bank and its start-up helpers, piece by piece (the flights are in test_startup.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vtolpose.estimator.core.calibration import ImuNoise
from vtolpose.estimator.core.measurements import GpsFix
from vtolpose.estimator.core.rotation import quat_from_euler, yaw_of
from vtolpose.estimator.core.state import FilterState, StateLayout
from vtolpose.estimator.gnss.gps_update import GpsUpdater
from vtolpose.estimator.inertial.heading_bank import (
    HeadingBank, HeadingBankOptions, circular_spread, rotated_about_down, with_bias_states,
)
from vtolpose.estimator.inertial.imu_delta import ImuDelta
from vtolpose.estimator.inertial.initializer import block_means
from vtolpose.estimator.inertial.propagator import ImuPropagator
from vtolpose.estimator.inertial.startup import velocity_from_fixes

G = 9.80665
NOISE = ImuNoise.isotropic(2e-3, 2e-5, 5e-2, 3e-3)


def level_state(yaw: float = 0.0) -> FilterState:
    state = FilterState(StateLayout("biases"))
    state.q = quat_from_euler(0.0, 0.0, yaw)
    state.cov = np.diag([1e-4] * 3 + [1e-4] * 3 + [1e-4, 1e-4, 0.0] + [1e-6] * 3 + [1e-4] * 3)
    return state


def test_a_hypothesis_is_the_state_turned_about_down() -> None:
    state = level_state(0.2)
    state.v = np.array([1.0, 0.0, 0.0])
    state.cov[6, 7] = state.cov[7, 6] = 3e-5
    turned = rotated_about_down(state, math.pi / 2)
    assert yaw_of(turned.q) == pytest.approx(0.2 + math.pi / 2)
    np.testing.assert_allclose(turned.v, state.v)  # velocity is the GPS's, not the attitude's
    assert np.all(turned.cov[8] == 0.0) and np.all(turned.cov[:, 8] == 0.0)
    assert turned.cov[6, 7] == pytest.approx(-3e-5)  # the tilt covariance turns with the frame


def test_circular_spread_wraps() -> None:
    mean, var = circular_spread(np.array([math.pi - 0.1, -math.pi + 0.1]), np.array([0.5, 0.5]), np.zeros(2))
    assert abs(abs(mean) - math.pi) < 1e-12 and var == pytest.approx(0.01)


def test_a_model_without_bias_states_gets_them_for_the_search() -> None:
    thesis = FilterState(StateLayout("thesis"))
    thesis.cov = np.eye(9) * 1e-4
    expanded = with_bias_states(thesis, np.full(3, 0.01), 0.1)
    assert expanded.layout.estimates_biases and expanded.cov.shape == (15, 15)
    np.testing.assert_allclose(np.diagonal(expanded.cov)[9:], [1e-4] * 3 + [1e-2] * 3)


def drive(bank: HeadingBank, accel_ned: np.ndarray, seconds: float, truth_yaw: float) -> None:
    """Fly the bank with a constant NED acceleration for ``seconds``; fixes at 10 Hz, exact."""
    body_f = np.array([[math.cos(truth_yaw), math.sin(truth_yaw), 0.0], [-math.sin(truth_yaw), math.cos(truth_yaw), 0.0], [0, 0, 1]]) @ (accel_ned - [0, 0, G])
    dt, p, v = 0.01, np.zeros(3), np.zeros(3)
    for k in range(int(seconds / dt)):
        t0, t1 = int(k * dt * 1e9), int((k + 1) * dt * 1e9)
        bank.propagate(ImuDelta(t0, t1, dt, np.zeros(3), body_f * dt))
        p, v = p + v * dt + 0.5 * accel_ned * dt * dt, v + accel_ned * dt
        if (k + 1) % 10 == 0:
            bank.update(GpsFix(t1, p.copy(), 0.02, 0.03))


def test_the_bank_waits_at_rest_and_places_the_heading_once_the_vehicle_accelerates() -> None:
    truth_yaw = 1.0
    bank = HeadingBank(HeadingBankOptions(), level_state(0.0), ImuPropagator(NOISE, G), GpsUpdater(np.zeros(3), None))
    drive(bank, np.zeros(3), 5.0, truth_yaw)  # at rest: every hypothesis predicts the fixes alike
    np.testing.assert_allclose(bank.weights, 1.0 / 8, atol=1e-9)
    assert bank.placed() is None
    drive(bank, np.array([0.5, 0.3, 0.0]), 5.0, truth_yaw)
    placed = bank.placed()
    assert placed is not None and abs(math.remainder(yaw_of(placed.q) - truth_yaw, 2 * math.pi)) < 3 * math.sqrt(placed.cov[8, 8])
    assert math.sqrt(placed.cov[8, 8]) < math.radians(10.0)


def test_the_placed_covariance_carries_what_the_heading_drags_along() -> None:
    # Hypotheses a few degrees apart that flew a turn: each took the sideways acceleration its heading error made
    # into its roll. The spread of the heading is then a spread of the roll too, one to one correlated; the placed
    # state must say so, or a later fix that corrects the heading leaves the roll where it was.
    bank = HeadingBank(HeadingBankOptions(), level_state(0.0), ImuPropagator(NOISE, G), GpsUpdater(np.zeros(3), None))
    yaws = np.radians([-4.0, -2.0, 0.0, 2.0, 4.0])
    roll_per_yaw = 0.2
    members = []
    for yaw in yaws:
        member = level_state(yaw)
        member.q = quat_from_euler(roll_per_yaw * yaw, 0.0, yaw)
        member.cov[8, 8] = 1e-6
        member.v = np.array([8.0, 0.0, 0.0]) + 0.5 * np.array([0.0, yaw, 0.0])
        members.append(member)
    bank.members = members
    bank.log_weights = np.log(np.array([0.1, 0.2, 0.4, 0.2, 0.1]))
    placed = bank.placed()
    assert placed is not None and yaw_of(placed.q) == pytest.approx(0.0, abs=1e-12)  # the heaviest
    spread = float(np.array([0.1, 0.2, 0.4, 0.2, 0.1]) @ yaws**2)
    assert placed.cov[8, 8] == pytest.approx(spread + 1e-6, rel=0.02)
    assert placed.cov[6, 8] == pytest.approx(roll_per_yaw * spread, rel=0.05)  # roll moves with the heading
    assert placed.cov[4, 8] == pytest.approx(0.5 * spread, rel=0.05)  # and the sideways velocity
    assert placed.cov[6, 6] >= 1e-4 + 0.9 * roll_per_yaw**2 * spread
    assert np.all(np.linalg.eigvalsh(placed.cov) > 0.0)


def test_velocity_from_fixes_tells_steady_flight_from_rest() -> None:
    t = (np.arange(11) * 0.1 * 1e9).astype(np.int64)
    moving = [GpsFix(int(tt), np.array([2.0 * tt * 1e-9, 0.0, 0.0]), 0.02, 0.03) for tt in t]
    v, cov = velocity_from_fixes(moving, int(t[-1]), 0.005)
    assert v[0] == pytest.approx(2.0, abs=1e-9) and np.all(np.sqrt(np.diag(cov)) < 0.2)
    assert velocity_from_fixes(moving[:3], int(t[-1]), 0.005) is None


def test_block_means_average_vibration_away() -> None:
    t = (np.arange(400) * 5e6).astype(np.int64)  # 200 Hz, 2 s
    vibration = np.column_stack([0.5 * np.sin(2 * np.pi * 50.0 * t * 1e-9)] * 3)
    assert vibration.std(axis=0).max() > 0.3 and block_means(t, vibration, 0.1).std(axis=0).max() < 1e-6


def test_the_outputs_say_when_the_heading_is_unknown_or_weak() -> None:
    from vtolpose.estimator.fusion import OutputPose
    from vtolpose.service.outputs.zenoh import pose_status
    from vtolpose.service.runtime.status import pose_quality

    def pose(aligned: bool, heading_sigma_deg: float) -> OutputPose:
        cov9 = np.diag([1e-4] * 6 + [math.radians(0.3) ** 2] * 2 + [math.radians(heading_sigma_deg) ** 2])
        pose_ix = np.ix_(np.r_[0:3, 6:9], np.r_[0:3, 6:9])
        return OutputPose(0, np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3), cov9, cov9[pose_ix],
                          np.zeros(3), aligned, True, 0, 0)

    unknown, weak, good = pose(False, 104.0), pose(True, 8.0), pose(True, 1.0)
    assert (pose_status(unknown, pose_quality(unknown)), pose_quality(unknown)) == ("heading_unaligned", 0)
    assert pose_status(weak, pose_quality(weak)) == "heading_weak" and 0 < pose_quality(weak) < pose_quality(good)
    assert pose_status(good, pose_quality(good)) == "ok"


def _one_fix_at_a_time(bank: HeadingBank, fix: GpsFix) -> tuple[list[FilterState], np.ndarray]:
    """The reference for :meth:`HeadingBank.update`: each hypothesis through the filter's own GPS update, its
    likelihood from numpy's log-determinant of the innovation covariance before the update."""
    from vtolpose.estimator.core.kalman import innovation_covariance
    from vtolpose.estimator.gnss.gps_update import GPS_COLS

    members, log_like = [], []
    cap = bank._likelihood_cap
    for member in bank.members:
        s = member.copy()
        sign, log_det = np.linalg.slogdet(innovation_covariance(s, GPS_COLS, bank.gps.model.jacobian(s), bank.gps.noise(fix)))
        out = bank.gps.update(s, fix)
        usable = sign > 0 and out.accepted and s.is_finite()
        log_like.append(-0.5 * (min(out.nis, cap) + log_det) if usable else -np.inf)
        members.append(s)
    return members, np.array(log_like)


@pytest.mark.parametrize("case", ["plain", "lever_arm", "broken", "gated"])
def test_one_compiled_call_updates_every_hypothesis_as_one_at_a_time_would(case: str) -> None:
    """The bank's fix is one compiled call over all hypotheses (gps_kernel.gps_update on their stack). Each hypothesis must
    come out bit for bit as the filter's own GPS update leaves it, its correction folded in; the weights
    as their likelihoods give them (to round-off: the log-determinant comes from a Cholesky factor, not LU).
    A hypothesis whose update fails or turns non-finite drops out; a fix no hypothesis takes changes nothing."""
    rng = np.random.default_rng(7)
    for trial in range(10):
        lever = rng.normal(size=3) * 0.4 if case == "lever_arm" else np.zeros(3)
        gps = GpsUpdater(lever, 1e-9 if case == "gated" else None)
        start = level_state(float(rng.uniform(-math.pi, math.pi)))
        start.v = rng.normal(size=3)
        bank = HeadingBank(HeadingBankOptions(), start, ImuPropagator(NOISE, G), gps)
        bank.update(GpsFix(0, np.zeros(3), 0.05, 0.08))  # placed at the first fix
        for member in bank.members:
            member.p = member.p + rng.normal(size=3) * 0.2
            member.b_a = member.b_a + rng.normal(size=3) * 0.01
            noise = rng.normal(size=(15, 15)) * 1e-3
            member.cov = member.cov + noise @ noise.T
        if case == "broken":
            bank.members[2].cov[0:3, 0:3] = -np.eye(3)  # its innovation covariance is not positive definite
            bank.members[5].cov[10, 10] = np.inf  # its update turns the state non-finite
        fix = GpsFix(1, rng.normal(size=3) * 0.3, float(rng.uniform(0.05, 0.5)), float(rng.uniform(0.05, 0.8)))
        before = bank.log_weights.copy()
        expected, log_like = _one_fix_at_a_time(bank, fix)
        bank.update(fix)
        for got, want in zip(bank.members, expected):
            for name in ("p", "v", "q", "b_g", "b_a", "cov"):
                assert np.array_equal(getattr(got, name), getattr(want, name), equal_nan=True), (case, trial, name)
        if case == "gated":
            assert np.array_equal(bank.log_weights, before) and bank.fixes == 0
            continue
        w = before + log_like
        w -= np.max(w) + math.log(np.sum(np.exp(w - np.max(w))))
        np.testing.assert_allclose(bank.log_weights, w, rtol=0, atol=1e-9)
        assert bank.fixes == 1
        if case == "broken":
            assert np.isneginf(log_like[[2, 5]]).all() and np.isneginf(bank.log_weights[[2, 5]]).all()


def test_equal_nis_weighs_the_hypothesis_with_the_tighter_prediction_higher() -> None:
    """A hypothesis' likelihood is a Gaussian's, −½ (NIS + log det S): two that predicted a fix equally well in
    NIS still differ by how sure they were. Each hypothesis here sits its own innovation sigma away from the
    fix (NIS 1 for all), with a different position variance: the weights follow 1/√det S exactly."""
    gps = GpsUpdater(np.zeros(3), None)
    bank = HeadingBank(HeadingBankOptions(hypotheses=4), level_state(), ImuPropagator(NOISE, G), gps)
    bank.update(GpsFix(0, np.zeros(3), 0.05, 0.08))  # placed at the first fix
    fix = GpsFix(1, np.array([1.0, 2.0, -0.5]), 0.05, 0.08)
    var_h, var_v = 0.05**2, 0.08**2
    log_dets = []
    for k, member in enumerate(bank.members):
        position_var = 1e-4 * 4.0**k
        member.cov[0:3, :] = 0.0
        member.cov[:, 0:3] = 0.0
        member.cov[0:3, 0:3] = np.eye(3) * position_var
        s = np.array([position_var + var_h, position_var + var_h, position_var + var_v])
        member.p = fix.p_ned - np.array([math.sqrt(s[0]), 0.0, 0.0])  # one sigma north of its prediction: NIS 1
        log_dets.append(float(np.sum(np.log(s))))
    before = bank.log_weights.copy()
    bank.update(fix)
    gained = bank.log_weights - before
    np.testing.assert_allclose(gained - gained[0], -0.5 * (np.array(log_dets) - log_dets[0]), rtol=0, atol=1e-9)
    assert np.all(np.diff(bank.log_weights) < 0.0)  # the tighter, the heavier
