"""IMU time update: analytic Jacobian against central differences, and integration accuracy."""

import numpy as np
import pytest

from estimator.calibration import ImuNoise
from estimator.propagator import ImuPropagator, error_transition, integrate_nominal, process_noise
from estimator.rotation import quat_exp, quat_from_euler, quat_log, quat_mul, quat_conj
from estimator.state import FilterState, StateLayout

G = np.array([0.0, 0.0, 9.81])
rng = np.random.default_rng(3)


def perturbed_step(x0, dx, gyro, accel, dt, layout):
    p, v, q, bg, ba = x0
    q_p = quat_mul(quat_exp(dx[6:9]), q)
    bg_p, ba_p = bg, ba
    if layout.estimates_biases:
        bg_p, ba_p = bg + dx[9:12], ba + dx[12:15]
    return integrate_nominal(p + dx[0:3], v + dx[3:6], q_p, bg_p, ba_p, gyro, accel, dt, G)[:3], (bg_p, ba_p)


def error_between(a, b, layout):
    (pa, va, qa), (bga, baa) = a
    (pb, vb, qb), (bgb, bab) = b
    err = [pa - pb, va - vb, quat_log(quat_mul(qa, quat_conj(qb)))]
    if layout.estimates_biases:
        err += [bga - bgb, baa - bab]
    return np.concatenate(err)


@pytest.mark.parametrize("variant", ["thesis", "biases"])
@pytest.mark.parametrize("dt", [0.008, 0.05])
def test_error_transition_matches_central_differences(variant, dt):
    layout = StateLayout(variant)
    n = layout.robot_dim
    x0 = (rng.normal(size=3), rng.normal(size=3), quat_from_euler(0.3, -0.2, 1.1), rng.normal(size=3) * 0.05, rng.normal(size=3) * 0.2)
    gyro = np.array([0.8, -1.5, 2.0])
    accel = np.array([1.0, -2.0, -9.0])
    F = error_transition(x0[2], x0[3], x0[4], gyro, accel, dt, layout)
    nominal = perturbed_step(x0, np.zeros(n), gyro, accel, dt, layout)
    h = 1e-6
    numeric = np.zeros((n, n))
    for i in range(n):
        d = np.zeros(n)
        d[i] = h
        plus = error_between(perturbed_step(x0, d, gyro, accel, dt, layout), nominal, layout)
        minus = error_between(perturbed_step(x0, -d, gyro, accel, dt, layout), nominal, layout)
        numeric[:, i] = (plus - minus) / (2 * h)
    assert np.allclose(F, numeric, atol=1e-7), np.abs(F - numeric).max()


def test_jacobian_test_would_catch_a_sign_error():
    layout = StateLayout("biases")
    x0 = (np.zeros(3), np.zeros(3), quat_from_euler(0.1, 0.2, 0.3), np.zeros(3), np.zeros(3))
    F = error_transition(x0[2], x0[3], x0[4], np.array([0.1, 0.2, 0.3]), np.array([0.5, 0.1, -9.8]), 0.01, layout)
    F_wrong = F.copy()
    F_wrong[3:6, 6:9] *= -1
    d = np.zeros(15)
    d[7] = 1e-6
    nominal = perturbed_step(x0, np.zeros(15), np.array([0.1, 0.2, 0.3]), np.array([0.5, 0.1, -9.8]), 0.01, layout)
    num = error_between(perturbed_step(x0, d, np.array([0.1, 0.2, 0.3]), np.array([0.5, 0.1, -9.8]), 0.01, layout), nominal, layout) / 1e-6
    assert np.allclose(F @ d / 1e-6, num, atol=1e-5)
    assert not np.allclose(F_wrong @ d / 1e-6, num, atol=1e-5)


def test_constant_rotation_and_acceleration_integrate_exactly():
    # Spin about body z at 1 rad/s while at rest in a level attitude: gravity is balanced.
    p, v, q = np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0])
    for _ in range(1000):
        p, v, q, _ = integrate_nominal(p, v, q, np.zeros(3), np.zeros(3), np.array([0, 0, 1.0]), np.array([0, 0, -9.81]), 0.001, G)
    assert np.allclose(quat_log(q), [0, 0, 1.0], atol=1e-9)
    assert np.allclose(p, 0, atol=1e-12) and np.allclose(v, 0, atol=1e-12)
    # Free fall: the accelerometer reads zero.
    p, v, q = np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0])
    for _ in range(100):
        p, v, q, _ = integrate_nominal(p, v, q, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), 0.01, G)
    assert np.allclose(v, [0, 0, 9.81]) and np.allclose(p, [0, 0, 0.5 * 9.81])


def test_process_noise_matches_white_noise_densities():
    noise = ImuNoise.isotropic(1e-3, 1e-4, 2e-2, 1e-3)
    Q = process_noise(quat_from_euler(0.2, 0.1, 1.0), 0.01, noise, StateLayout("biases"))
    assert np.allclose(np.diag(Q)[3:6], 2e-2**2 * 0.01)  # velocity random walk
    assert np.allclose(np.diag(Q)[6:9], 1e-3**2 * 0.01)  # angle random walk
    assert np.allclose(np.diag(Q)[9:12], 1e-4**2 * 0.01)
    assert np.allclose(Q, Q.T)
    assert np.all(np.linalg.eigvalsh(Q) >= -1e-18)


def test_propagate_keeps_landmark_block_and_updates_cross_terms():
    layout = StateLayout("biases")
    state = FilterState(layout)
    state.landmarks = np.zeros((2, 6))
    A = rng.normal(size=(27, 27))
    state.cov = A @ A.T
    mm_before = state.cov[15:, 15:].copy()
    prop = ImuPropagator(ImuNoise.isotropic(1e-3, 1e-4, 2e-2, 1e-3), 9.81)
    F = error_transition(state.q, state.b_g, state.b_a, np.array([0.1, 0, 0]), np.array([0, 0, -9.81]), 0.01, layout)
    cross = F @ state.cov[:15, 15:]
    prop.propagate(state, np.array([0.1, 0, 0]), np.array([0, 0, -9.81]), 0.01)
    assert np.array_equal(state.cov[15:, 15:], mm_before)
    assert np.allclose(state.cov[:15, 15:], cross)
    assert np.allclose(state.cov, state.cov.T)


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
    gyro, accel, dt = np.array([0.5, -0.7, 1.2]), np.array([0.3, -0.2, -9.7]), 0.008
    a_w = ImuPropagator(noise, 9.81).propagate(state, gyro, accel, dt, extra_horizontal_accel=0.5)
    p, v, q, a_ref = integrate_nominal(before.p, before.v, before.q, before.b_g, before.b_a, gyro, accel, dt, G)
    F = error_transition(before.q, before.b_g, before.b_a, gyro, accel, dt, layout)
    Q = process_noise(before.q, dt, noise, layout, 0.5)
    n = layout.robot_dim
    assert np.allclose(state.p, p, atol=1e-14) and np.allclose(state.v, v, atol=1e-14)
    assert np.allclose(state.q, q, atol=1e-15) and np.allclose(a_w, a_ref)
    assert np.allclose(state.cov[:n, :n], F @ before.cov[:n, :n] @ F.T + Q, atol=1e-12)
    assert np.allclose(state.cov[:n, n:], F @ before.cov[:n, n:], atol=1e-12)
