"""Levelling by gravity: Jacobian against central differences; it corrects tilt, never heading."""

import numpy as np

from vtolpose.estimator.inertial.gravity_update import GravityLeveller, GravityModel
from vtolpose.estimator.core.rotation import euler_from_quat, quat_conj, quat_exp, quat_from_euler, quat_log, quat_mul, quat_to_rot
from vtolpose.estimator.core.state import FilterState, StateLayout


def make_state(variant="biases"):
    s = FilterState(StateLayout(variant))
    s.q = quat_from_euler(0.3, -0.25, 1.2)
    s.b_a = np.array([0.05, -0.02, 0.03]) if variant == "biases" else np.zeros(3)
    s.cov = np.eye(s.robot_dim) * 1e-2
    return s


def test_jacobian_matches_central_differences():
    model = GravityModel(9.81)
    s = make_state()
    cols, H = model.jacobian(s)
    numeric = np.zeros((3, len(cols)))
    h = 1e-6
    for j, col in enumerate(cols):
        for sign in (1, -1):
            t = s.copy()
            d = np.zeros(15)
            d[col] = sign * h
            t.q = quat_mul(quat_exp(d[6:9]), t.q)
            t.b_a = t.b_a + d[12:15]
            numeric[:, j] += sign * model.predict(t) / (2 * h)
    assert np.allclose(H, numeric, atol=1e-6)
    assert np.allclose(H[:, 2], 0.0)  # heading does not change the gravity direction


def test_levelling_recovers_tilt_and_leaves_heading():
    true_q = quat_from_euler(0.1, -0.2, 0.7)
    f = -quat_to_rot(true_q).T @ np.array([0, 0, 9.81])
    for variant in ("thesis", "biases"):
        s = make_state(variant)
        s.b_a[:] = 0.0
        s.q = start = quat_from_euler(0.15, -0.12, 0.7)
        s.cov[6:9, 6:9] = np.eye(3) * np.radians(10) ** 2
        leveller = GravityLeveller(9.81, 0.2, gate=None)
        held = np.zeros(s.dim, dtype=bool)
        held[8] = True
        for _ in range(30):
            leveller.update(s, f, held)
        roll, pitch, _ = euler_from_quat(s.q)
        assert abs(roll - 0.1) < 2e-3 and abs(pitch + 0.2) < 2e-3
        # The correction is a rotation about horizontal world axes only (second-order residue).
        correction = quat_log(quat_mul(s.q, quat_conj(start)))
        assert abs(correction[2]) < 5e-3 < np.linalg.norm(correction[:2])
