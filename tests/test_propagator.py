"""IMU time update: analytic Jacobian against central differences, fast path against reference."""

import math

import numpy as np
import pytest

from vtolpose.estimator.core.calibration import ImuNoise
from vtolpose.estimator.inertial.imu_delta import ImuDelta, ImuDownsampler
from vtolpose.estimator.inertial.propagator import ImuPropagator, process_noise

from propagation_oracle import error_transition, integrate_nominal
from vtolpose.estimator.core.rotation import quat_conj, quat_exp, quat_from_euler, quat_log, quat_mul
from vtolpose.estimator.core.state import FilterState, StateLayout

G = np.array([0.0, 0.0, 9.81])
rng = np.random.default_rng(3)


def perturbed_step(x0, dx, dtheta, dvel, dt, layout):
    p, v, q, bg, ba = x0
    q_p = quat_mul(quat_exp(dx[6:9]), q)
    bg_p, ba_p = bg, ba
    if layout.estimates_biases:
        bg_p, ba_p = bg + dx[9:12], ba + dx[12:15]
    return integrate_nominal(p + dx[0:3], v + dx[3:6], q_p, bg_p, ba_p, dtheta, dvel, dt, G)[:3], (bg_p, ba_p)


def error_between(a, b, layout):
    (pa, va, qa), (bga, baa) = a
    (pb, vb, qb), (bgb, bab) = b
    err = [pa - pb, va - vb, quat_log(quat_mul(qa, quat_conj(qb)))]
    if layout.estimates_biases:
        err += [bga - bgb, baa - bab]
    return np.concatenate(err)


def numeric_transition(x0, dtheta, dvel, dt, layout, h=1e-6):
    n = layout.robot_dim
    nominal = perturbed_step(x0, np.zeros(n), dtheta, dvel, dt, layout)
    out = np.zeros((n, n))
    for i in range(n):
        d = np.zeros(n)
        d[i] = h
        plus = error_between(perturbed_step(x0, d, dtheta, dvel, dt, layout), nominal, layout)
        minus = error_between(perturbed_step(x0, -d, dtheta, dvel, dt, layout), nominal, layout)
        out[:, i] = (plus - minus) / (2 * h)
    return out


@pytest.mark.parametrize("variant", ["thesis", "biases"])
@pytest.mark.parametrize("dt", [0.008, 0.05])
def test_error_transition_matches_central_differences(variant, dt):
    layout = StateLayout(variant)
    x0 = (rng.normal(size=3), rng.normal(size=3), quat_from_euler(0.3, -0.2, 1.1), rng.normal(size=3) * 0.05, rng.normal(size=3) * 0.2)
    dtheta = np.array([0.8, -1.5, 2.0]) * dt
    dvel = np.array([1.0, -2.0, -9.0]) * dt
    F = error_transition(x0[2], x0[3], x0[4], dtheta, dvel, dt, layout)
    assert np.allclose(F, numeric_transition(x0, dtheta, dvel, dt, layout), atol=1e-7)


def propagated(state: FilterState, delta: ImuDelta, prop: ImuPropagator) -> FilterState:
    out = state.copy()
    prop.propagate(out, delta)
    return out


@pytest.mark.parametrize("variant", ["thesis", "biases"])
def test_the_propagator_moves_the_covariance_as_its_own_step_moves_errors(variant):
    """The transition the fast propagator applies to the covariance equals central differences of its
    own nominal step, independently of the reference functions.

    With a map of landmarks whose cross-covariance with the robot is ``[I 0]``, the propagated
    cross-covariance ``F P_rm`` is F itself; a sign or a block wrong in the propagator shows there.
    """
    layout = StateLayout(variant)
    n = layout.robot_dim
    prop = ImuPropagator(ImuNoise.isotropic(3e-4, 2e-5, 2e-3, 3e-4), 9.81)
    state = FilterState(layout)
    state.p, state.v = np.array([1.0, -2.0, -30.0]), np.array([6.0, 1.5, -0.4])
    state.q = quat_from_euler(0.3, -0.2, 1.1)
    if layout.estimates_biases:
        state.b_g, state.b_a = np.array([0.01, -0.02, 0.015]), np.array([0.1, -0.05, 0.2])
    n_landmarks = -(-n // 6)
    state.landmarks = np.zeros((n_landmarks, 6))
    state.cov = np.eye(n + 6 * n_landmarks)
    state.cov[:n, n:2 * n] = state.cov[n:2 * n, :n] = 0.5 * np.eye(n)  # positive definite, cross block ∝ I
    dt = 0.02
    delta = ImuDelta(0, int(dt * 1e9), dt, np.array([0.8, -1.5, 2.0]) * dt, np.array([1.0, -2.0, -9.0]) * dt)
    F = propagated(state, delta, prop).cov[:n, n:2 * n] / 0.5
    nominal = propagated(state, delta, prop)
    h, numeric = 1e-6, np.zeros((n, n))
    for i in range(n):
        columns = []
        for sign in (1.0, -1.0):
            d = np.zeros(n)
            d[i] = sign * h
            moved = state.copy()
            moved.p, moved.v = moved.p + d[0:3], moved.v + d[3:6]
            moved.q = quat_mul(quat_exp(d[6:9]), moved.q)
            if layout.estimates_biases:
                moved.b_g, moved.b_a = moved.b_g + d[9:12], moved.b_a + d[12:15]
            after = propagated(moved, delta, prop)
            err = [after.p - nominal.p, after.v - nominal.v, quat_log(quat_mul(after.q, quat_conj(nominal.q)))]
            if layout.estimates_biases:
                err += [after.b_g - nominal.b_g, after.b_a - nominal.b_a]
            columns.append(np.concatenate(err))
        numeric[:, i] = (columns[0] - columns[1]) / (2 * h)
    assert np.abs(F - np.eye(n)).max() > 0.1  # the step really couples the errors
    assert np.allclose(F, numeric, atol=1e-7)


def one_sample_deltas(rate_hz, n, gyro, accel):
    """Deltas of a downsampler that emits at every sample."""
    ds = ImuDownsampler(max_rate_hz=10 * rate_hz)
    t = (np.arange(n) * 1e9 / rate_hz).astype(np.int64)
    return [d for d in (ds.add(int(ti), gyro, accel) for ti in t) if d is not None]


def test_constant_rotation_and_free_fall_integrate_exactly():
    p, v, q = np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0])
    for d in one_sample_deltas(1000, 1001, np.array([0, 0, 1.0]), np.array([0, 0, -9.81])):
        p, v, q, _ = integrate_nominal(p, v, q, np.zeros(3), np.zeros(3), d.dtheta, d.dvel, d.dt, G)
    assert np.allclose(quat_log(q), [0, 0, 1.0], atol=1e-9)
    assert np.allclose(p, 0, atol=1e-12) and np.allclose(v, 0, atol=1e-12)
    p, v, q = np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0])
    for d in one_sample_deltas(100, 101, np.zeros(3), np.zeros(3)):
        p, v, q, _ = integrate_nominal(p, v, q, np.zeros(3), np.zeros(3), d.dtheta, d.dvel, d.dt, G)
    assert np.allclose(v, [0, 0, 9.81]) and np.allclose(p, [0, 0, 0.5 * 9.81])


def test_downsampled_deltas_follow_a_rotating_accelerating_body():
    """Deltas over 4 samples integrate the same motion as per-sample steps (within mm)."""
    rate, n = 200.0, 2001
    t = np.arange(n) / rate
    gyro = np.stack([0.5 * np.sin(t), 0.3 * np.cos(2 * t), 0.8 + 0 * t], axis=1)
    accel = np.stack([np.cos(t), 0.5 * np.sin(3 * t), -9.81 + 0.2 * np.cos(t)], axis=1)
    results = []
    for max_rate in (10 * rate, rate / 4):
        ds = ImuDownsampler(max_rate)
        p, v, q = np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0])
        for i in range(n):
            d = ds.add(int(round(t[i] * 1e9)), gyro[i], accel[i])
            if d is not None:
                p, v, q, _ = integrate_nominal(p, v, q, np.zeros(3), np.zeros(3), d.dtheta, d.dvel, d.dt, G)
        results.append((p, v, q))
    (p1, v1, q1), (p4, v4, q4) = results
    assert np.linalg.norm(p1 - p4) < 2e-3 and np.linalg.norm(v1 - v4) < 1e-3
    assert np.linalg.norm(quat_log(quat_mul(q1, quat_conj(q4)))) < 1e-6


def test_flush_and_hold_split_a_step_at_a_measurement_time():
    ds = ImuDownsampler(max_rate_hz=50.0)  # deltas of >= 18 ms from 5 ms samples
    g, a = np.array([0.1, 0.0, 0.0]), np.array([0.0, 0.0, -9.8])
    for k in range(3):
        assert ds.add(k * 5_000_000, g, a) is None
    partial = ds.flush()
    assert partial.t0_ns == 0 and partial.t1_ns == 10_000_000 and partial.dt == pytest.approx(0.01)
    held = ds.hold(12_000_000)
    assert held.t0_ns == 10_000_000 and held.dt == pytest.approx(0.002)
    assert np.allclose(held.dtheta, g * 0.002)
    nxt = [ds.add(k * 5_000_000, g, a) for k in range(3, 8)]
    first = next(d for d in nxt if d is not None)
    assert first.t0_ns == 12_000_000  # the next delta starts where the hold ended


def test_process_noise_matches_white_noise_densities():
    noise = ImuNoise.isotropic(1e-3, 1e-4, 2e-2, 1e-3)
    Q = process_noise(quat_from_euler(0.2, 0.1, 1.0), 0.01, noise, StateLayout("biases"))
    assert np.allclose(np.diag(Q)[3:6], 2e-2**2 * 0.01)  # velocity random walk
    assert np.allclose(np.diag(Q)[6:9], 1e-3**2 * 0.01)  # angle random walk
    assert np.allclose(np.diag(Q)[9:12], 1e-4**2 * 0.01)
    assert np.allclose(Q, Q.T) and np.all(np.linalg.eigvalsh(Q) >= -1e-18)


@pytest.mark.parametrize("variant", ["thesis", "biases"])
@pytest.mark.parametrize("isotropic", [True, False])
def test_fast_propagate_equals_reference_functions(variant, isotropic):
    layout = StateLayout(variant)
    noise = ImuNoise.isotropic(3e-4, 2e-5, 2e-3, 3e-4) if isotropic else ImuNoise(
        np.array([3e-4, 4e-4, 5e-4]), np.full(3, 2e-5), np.array([2e-3, 3e-3, 1e-3]), np.full(3, 3e-4)
    )
    state = FilterState(layout)
    state.p, state.v = rng.normal(size=3), rng.normal(size=3)
    state.q = quat_from_euler(0.4, -0.3, 2.0)
    state.b_g, state.b_a = rng.normal(size=3) * 0.01, rng.normal(size=3) * 0.1
    state.landmarks = np.zeros((1, 6))
    A = rng.normal(size=(layout.robot_dim + 6,) * 2)
    state.cov = A @ A.T
    before = state.copy()
    prop = ImuPropagator(noise, 9.81)
    for dt in (0.008, 0.011):  # the second step checks the dt-polynomial noise for a new dt
        before = state.copy()
        delta = ImuDelta(0, int(dt * 1e9), dt, np.array([0.5, -0.7, 1.2]) * dt, np.array([0.3, -0.2, -9.7]) * dt)
        a_w = prop.propagate(state, delta, extra_horizontal_accel=0.5)
        p, v, q, a_ref = integrate_nominal(before.p, before.v, before.q, before.b_g, before.b_a, delta.dtheta, delta.dvel, dt, G)
        F = error_transition(before.q, before.b_g, before.b_a, delta.dtheta, delta.dvel, dt, layout)
        Q = process_noise(before.q, dt, noise, layout, 0.5)
        n = layout.robot_dim
        assert np.allclose(state.p, p, atol=1e-14) and np.allclose(state.v, v, atol=1e-14)
        assert np.allclose(state.q, q, atol=1e-15) and np.allclose(a_w, a_ref)
        assert np.allclose(state.cov[:n, :n], F @ before.cov[:n, :n] @ F.T + Q, atol=1e-10)
        assert np.allclose(state.cov[:n, n:], F @ before.cov[:n, n:], atol=1e-10)
        assert np.array_equal(state.cov[n:, n:], before.cov[n:, n:])


@pytest.mark.parametrize("variant", ["thesis", "biases"])
def test_compiled_step_is_bit_for_bit_the_interpreted_one(variant):
    """The compiled step (numba) must do the interpreted step's operations in the same order: the filter's
    numbers do not depend on which runs. Also at a zero rotation (the small-angle branches)."""
    from vtolpose.estimator.inertial import propagation_kernel as kernel

    n = StateLayout(variant).robot_dim
    local = np.random.default_rng(7)
    for k in range(20):
        q = quat_from_euler(*local.uniform(-3.0, 3.0, 3))
        p, v, b_g, b_a = (local.normal(size=3) * s for s in (10.0, 2.0, 0.01, 0.1))
        dt = float(local.uniform(0.002, 0.05))
        dtheta = np.zeros(3) if k == 0 else local.normal(size=3) * dt
        dvel = local.normal(size=3) * dt + np.array([0.0, 0.0, -9.8 * dt])
        A = local.normal(size=(n, n))
        cov, Q = A @ A.T, np.diag(local.uniform(1e-9, 1e-6, n))
        results = []
        for step in (kernel.step, kernel.step.py_func):
            F, out = np.eye(n), np.empty(kernel.OUT_LEN)
            grown = step(p, v, q, b_g, b_a, dtheta, dvel, dt, 9.81, F, cov, Q, variant == "biases", out)
            results.append((grown, F, out))
        for compiled, interpreted in zip(*results):
            assert np.array_equal(compiled, interpreted)
        terms = local.normal(size=(6, n, n))
        for extra2 in (0.0, float(local.uniform(0.01, 4.0))):
            c = [terms[i] + extra2 * terms[i + 3] for i in range(3)] if extra2 else list(terms[:3])
            numpy_q = (c[0] + (c[1] + c[2] * dt) * dt) * dt  # the expression the interpreted filter used
            assert np.array_equal(kernel.noise_from_terms(terms, extra2, dt), numpy_q)


@pytest.mark.parametrize("variant, unaligned", [("thesis", False), ("biases", False), ("thesis", True), ("biases", True)])
def test_a_compiled_sequence_of_steps_is_bit_for_bit_the_steps_one_by_one(variant, unaligned):
    """propagate_steps: the states, covariances and running horizontal acceleration after each step are those
    of propagate called step by step (the estimator's loop), whatever dt each step has; while the heading is
    unknown, with the extra horizontal noise the estimator adds from the running mean before each step
    (its floor, or twice the mean's distance from the reading at rest, whichever is larger: both occur)."""
    layout = StateLayout(variant)
    local = np.random.default_rng(11)
    state = FilterState(layout)
    state.p, state.v, state.q = local.normal(size=3), local.normal(size=3), quat_from_euler(0.3, -0.2, 1.9)
    state.b_g, state.b_a = local.normal(size=3) * 0.01, local.normal(size=3) * 0.1
    A = local.normal(size=(layout.robot_dim,) * 2)
    state.cov = A @ A.T
    dts = np.array([0.01, 0.01, 0.0095, 0.0105, 0.01, 0.02])
    deltas = np.hstack([local.normal(size=(6, 3)) * dts[:, None],
                        (local.normal(size=(6, 3)) + [0.0, 0.0, -9.8]) * dts[:, None]])
    horizontal, average_s = np.array([0.2, -0.1]), 0.5
    floor, at_rest = 0.3, np.array([0.05, 0.02])
    prop = ImuPropagator(ImuNoise.isotropic(3e-4, 2e-5, 2e-3, 3e-4), 9.81)
    states, covs, means = prop.propagate_steps(state, deltas, dts, horizontal, average_s,
                                               floor if unaligned else None, at_rest)
    # With the state before the steps as a first row: that row, then the same rows.
    with_start = prop.propagate_steps(state, deltas, dts, horizontal, average_s, floor if unaligned else None, at_rest,
                                      start_row=True)
    assert np.array_equal(with_start[0][0], np.concatenate([state.p, state.v, state.q]))
    assert np.array_equal(with_start[1][0], state.cov) and np.array_equal(with_start[2][0], horizontal)
    for before, rows in zip(with_start, (states, covs, means)):
        assert np.array_equal(before[1:], rows)
    hx, hy = horizontal.tolist()
    extras = []
    for j, dt in enumerate(dts.tolist()):
        extra = 0.0
        if unaligned:
            ax, ay = hx - at_rest[0], hy - at_rest[1]
            extra = max(floor, 2.0 * math.sqrt(ax * ax + ay * ay))
            extras.append(extra > floor)
        a_w = prop.propagate(state, ImuDelta(0, 1, dt, deltas[j, 0:3], deltas[j, 3:6]), extra)
        keep = average_s / (average_s + dt)
        hx, hy = keep * hx + (1.0 - keep) * a_w[0], keep * hy + (1.0 - keep) * a_w[1]
        assert np.array_equal(states[j], np.concatenate([state.p, state.v, state.q]))
        assert np.array_equal(covs[j], state.cov)
        assert means[j].tolist() == [hx, hy]
    assert not unaligned or (any(extras) and not all(extras))
    state.landmarks, state.cov = np.zeros((1, 6)), np.eye(layout.robot_dim + 6)
    assert prop.propagate_steps(state, deltas, dts, horizontal, average_s) is None  # a map: step by step


@pytest.mark.parametrize("variant", ["thesis", "biases"])
def test_states_propagated_together_are_bit_for_bit_each_propagated_alone(variant):
    """propagate_all (the heading hypotheses, one compiled call) equals propagate on each state; a state with a
    map, or of another layout, sends them all step by step."""
    layout = StateLayout(variant)
    local = np.random.default_rng(5)
    states = []
    for k in range(8):
        state = FilterState(layout)
        state.p, state.v, state.q = local.normal(size=3), local.normal(size=3), quat_from_euler(0.1, -0.2, k * 0.8)
        state.b_g, state.b_a = local.normal(size=3) * 0.01, local.normal(size=3) * 0.1
        A = local.normal(size=(layout.robot_dim,) * 2)
        state.cov = A @ A.T
        states.append(state)
    alone = [s.copy() for s in states]
    prop = ImuPropagator(ImuNoise.isotropic(3e-4, 2e-5, 2e-3, 3e-4), 9.81)
    for dt in (0.01, 0.012):
        delta = ImuDelta(0, 1, dt, local.normal(size=3) * dt, (local.normal(size=3) + [0.0, 0.0, -9.8]) * dt)
        assert prop.propagate_all(states, delta)
        for state in alone:
            prop.propagate(state, delta)
        for together, single in zip(states, alone):
            for name in ("p", "v", "q", "cov"):
                assert np.array_equal(getattr(together, name), getattr(single, name)), name
    deltas = np.hstack([local.normal(size=(5, 3)) * 0.01, (local.normal(size=(5, 3)) + [0.0, 0.0, -9.8]) * 0.01])
    dts = np.array([0.01, 0.0095, 0.0105, 0.01, 0.02])
    assert prop.propagate_all_run(states, deltas, dts)  # a run of deltas in one call: each in turn, as above
    for dt, delta in zip(dts.tolist(), deltas):
        assert prop.propagate_all(alone, ImuDelta(0, 1, dt, delta[0:3], delta[3:6]))
    for together, single in zip(states, alone):
        for name in ("p", "v", "q", "cov"):
            assert np.array_equal(getattr(together, name), getattr(single, name)), name
    other = FilterState(StateLayout("thesis" if variant == "biases" else "biases"))
    mapped = states[0].copy()
    mapped.landmarks, mapped.cov = np.zeros((1, 6)), np.eye(layout.robot_dim + 6)
    for odd in (other, mapped):
        before = [s.p.copy() for s in states]
        assert not prop.propagate_all(states + [odd], delta)
        assert not prop.propagate_all_run(states + [odd], deltas, dts)
        assert all(np.array_equal(s.p, p) for s, p in zip(states, before))  # nothing done


def test_the_compiled_kernels_are_not_compiled_again_during_a_replay(tmp_path):
    """One machine-code version of the step (and of the small update) serves every call of a replay with
    camera, landmarks, the heading bank's other layout, GPS, levelling and rest: another would be compiled
    mid-flight, a second-long stall."""
    from vtolpose.config import load_config
    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.drivers.simulator import simulate_flight
    from vtolpose.drivers.simulator.export import write_flight
    from vtolpose.drivers.simulator.render import default_camera
    from vtolpose.estimator.inertial import propagation_kernel as kernel
    from vtolpose.service.replay.session import replay

    from vtolpose.estimator.core import update_kernel

    write_flight(simulate_flight("book", 8.0, 1), tmp_path / "book", camera=default_camera())
    dataset = Dataset.open(tmp_path / "book")
    from vtolpose.estimator.inertial import sample_kernel

    def compiled() -> list[set]:
        return [set(f.signatures) for f in (kernel.step, kernel.noise_from_terms, kernel.step_run, kernel.step_all,
                                             kernel.step_all_run,
                                             update_kernel.small_update, update_kernel.small_inverse, update_kernel.gauge_transfer, gps_kernel.gps_update, gps_kernel.filter_fix,
                                             sample_kernel.downsample_run, sample_kernel.stillness_run,
                                             sample_kernel.screen_rows, sample_kernel.plain_run, sample_kernel.level_run,
                                             sample_kernel.to_time)]
    from vtolpose.estimator.gnss import gps_kernel

    for module in (kernel, update_kernel, gps_kernel, sample_kernel):
        module.warm_up()
    before = compiled()
    for variant in ("thesis", "biases"):
        cfg = load_config(None, {"estimator": {"variant": variant, "heading": {"source": "gps"}}, "features": {"detector": "orb"}})
        result = replay(dataset, cfg, ["imu", "camera", "gps"])
        assert result.estimator.state is not None and result.estimator.state.n_landmarks > 0
        replay(dataset, cfg, ["imu", "gps"])  # runs of IMU samples: the compiled sequences of steps
    assert compiled() == before
