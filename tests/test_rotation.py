"""Pins every rotation and frame convention: Hamilton, scalar first, body→world, NED/FRD."""

import numpy as np
import pytest

from vtolpose.estimator.core import frames
from vtolpose.estimator.core.rotation import (
    euler_from_quat,
    quat_conj,
    quat_exp,
    quat_from_euler,
    quat_log,
    quat_mul,
    quat_exp_of,
    quat_normalize,
    quat_product,
    quat_slerp,
    quat_to_rot,
    right_jacobian,
    rot_of,
    rot_to_quat,
    rotate,
    rotation_angle,
    rotvec_quat,
    skew,
    so3_exp,
    so3_log,
    yaw_of,
)

rng = np.random.default_rng(7)


def random_quats(n):
    return quat_normalize(rng.normal(size=(n, 4)))


def test_hamilton_product_rules():
    i, j, k = np.array([0, 1, 0, 0.0]), np.array([0, 0, 1, 0.0]), np.array([0, 0, 0, 1.0])
    assert np.allclose(quat_mul(i, j), k)  # Hamilton: ij = k (JPL would give -k)
    assert np.allclose(quat_mul(j, k), i)
    assert np.allclose(quat_mul(k, i), j)
    assert np.allclose(quat_mul(i, i), [-1, 0, 0, 0])


def test_scalar_first_and_body_to_world():
    # A 90° yaw (about down): the body's forward axis points east in NED.
    q = quat_from_euler(0.0, 0.0, np.pi / 2)
    assert q[0] == pytest.approx(np.cos(np.pi / 4))  # scalar first
    assert np.allclose(quat_to_rot(q) @ [1, 0, 0], [0, 1, 0])
    # Pitch up 90°: forward points up, i.e. -down.
    assert np.allclose(quat_to_rot(quat_from_euler(0, np.pi / 2, 0)) @ [1, 0, 0], [0, 0, -1], atol=1e-12)
    # Roll right 90°: the right axis points down.
    assert np.allclose(quat_to_rot(quat_from_euler(np.pi / 2, 0, 0)) @ [0, 1, 0], [0, 0, 1], atol=1e-12)


def test_rotation_matrix_is_transpose_of_thesis_eq_3_31():
    q0, q1, q2, q3 = quat_normalize(np.array([0.9, 0.1, -0.3, 0.2]))
    r_bw = np.array(
        [
            [q0**2 + q1**2 - q2**2 - q3**2, 2 * (q1 * q2 + q0 * q3), 2 * (q1 * q3 - q0 * q2)],
            [2 * (q1 * q2 - q0 * q3), q0**2 - q1**2 + q2**2 - q3**2, 2 * (q2 * q3 + q0 * q1)],
            [2 * (q1 * q3 + q0 * q2), 2 * (q2 * q3 - q0 * q1), q0**2 - q1**2 - q2**2 + q3**2],
        ]
    )
    assert np.allclose(quat_to_rot([q0, q1, q2, q3]), r_bw.T)


def test_composition_matches_matrix_product():
    a, b = random_quats(2)
    assert np.allclose(quat_to_rot(quat_mul(a, b)), quat_to_rot(a) @ quat_to_rot(b))
    assert np.allclose(quat_to_rot(quat_conj(a)), quat_to_rot(a).T)


def test_matrix_quaternion_round_trip_all_branches():
    qs = np.vstack([random_quats(200), quat_exp(np.array([[np.pi - 1e-9, 0, 0], [0, np.pi, 0], [0, 0, np.pi]]))])
    back = rot_to_quat(quat_to_rot(qs))
    assert np.allclose(np.abs(np.sum(back * quat_normalize(qs), axis=-1)), 1.0)
    assert np.all(back[:, 0] >= 0)


def test_exp_log_round_trip_and_small_angles():
    rv = rng.normal(size=(100, 3))
    rv *= (rng.uniform(0, np.pi - 1e-3, size=100) / np.linalg.norm(rv, axis=1))[:, None]
    assert np.allclose(quat_log(quat_exp(rv)), rv)
    tiny = np.array([1e-12, -2e-12, 3e-12])
    assert np.allclose(quat_log(quat_exp(tiny)), tiny, rtol=1e-6, atol=0)
    assert np.allclose(so3_log(so3_exp(rv[:5])), rv[:5])


def test_exp_is_rodrigues():
    rv = np.array([0.3, -0.2, 0.5])
    angle = np.linalg.norm(rv)
    k = skew(rv / angle)
    rodrigues = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
    assert np.allclose(so3_exp(rv), rodrigues)


def test_skew_is_cross_product():
    a, b = rng.normal(size=(2, 3))
    assert np.allclose(skew(a) @ b, np.cross(a, b))


def test_euler_round_trip_zyx_order():
    angles = np.array([0.2, -0.4, 2.5])
    q = quat_from_euler(*angles)
    assert np.allclose(euler_from_quat(q), angles)
    rz = so3_exp([0, 0, angles[2]])
    ry = so3_exp([0, angles[1], 0])
    rx = so3_exp([angles[0], 0, 0])
    assert np.allclose(quat_to_rot(q), rz @ ry @ rx)
    assert yaw_of(q) == pytest.approx(2.5)


def test_slerp_midpoint_and_shortest_arc():
    a = quat_from_euler(0, 0, 0.0)
    b = quat_from_euler(0, 0, 1.0)
    assert yaw_of(quat_slerp(a, b, 0.5)) == pytest.approx(0.5)
    assert yaw_of(quat_slerp(a, -b, 0.25)) == pytest.approx(0.25)  # -b is the same attitude


def test_rotation_angle_precise_for_small_angles():
    a = random_quats(1)[0]
    b = quat_mul(a, quat_exp(np.array([0, 1e-7, 0])))
    assert rotation_angle(a, b) == pytest.approx(1e-7, rel=1e-5)


def test_ned_enu_and_frd_flu():
    assert np.allclose(frames.ned_to_enu([1, 2, 3]), [2, 1, -3])
    assert np.allclose(frames.enu_to_ned(frames.ned_to_enu([1, 2, 3])), [1, 2, 3])
    assert np.allclose(frames.frd_to_flu([1, 2, 3]), [1, -2, -3])
    assert np.allclose(quat_to_rot(frames.Q_ENU_NED), frames.R_ENU_NED)
    assert np.allclose(quat_to_rot(frames.Q_FLU_FRD), frames.R_FLU_FRD)


def test_attitude_conversion_to_enu_flu_is_consistent_with_vectors():
    q = random_quats(1)[0]
    v_frd = rng.normal(size=3)
    v_ned = quat_to_rot(q) @ v_frd
    q_enu = frames.q_ned_frd_to_enu_flu(q)
    assert np.allclose(quat_to_rot(q_enu) @ frames.frd_to_flu(v_frd), frames.ned_to_enu(v_ned))
    back = frames.q_enu_flu_to_ned_frd(q_enu)
    assert rotation_angle(back, q) < 1e-12
    # Level and nose north: in ENU (yaw counted from east, counter-clockwise) that is +90°.
    assert yaw_of(frames.q_ned_frd_to_enu_flu(np.array([1.0, 0, 0, 0]))) == pytest.approx(np.pi / 2)


# The scalar primitives the per-sample paths and the compiled kernels share (rotation.py's docstring).


def test_the_scalar_product_and_rotation_are_the_array_ones():
    a, b = random_quats(2)
    assert np.array_equal(np.array(quat_product(*a, *b)), quat_mul(a, b))
    v = rng.normal(size=3)
    assert np.allclose(rotate(*a, *v), quat_to_rot(a) @ v, atol=1e-14)
    assert np.array_equal(np.array(rot_of(*a)), quat_to_rot(a))
    stack = random_quats(5)
    assert np.array_equal(quat_to_rot(stack), np.stack([np.array(rot_of(*q)) for q in stack]))


@pytest.mark.parametrize("phi", [np.array([0.3, -1.2, 0.7]), np.array([2.9, 0.1, -0.4]), np.array([1e-7, -2e-7, 3e-8]),
                                 np.zeros(3)])
def test_right_jacobian_matches_central_differences(phi):
    """Exp(φ + δ) = Exp(φ) Exp(Jr(φ) δ) to first order: column i of Jr is the derivative of
    Log(Exp(φ)ᵀ Exp(φ + h eᵢ)) in h, taken by central differences (navlie's way of checking a Jacobian)."""
    h = 1e-6
    numeric = np.empty((3, 3))
    base_t = so3_exp(phi).T
    for i in range(3):
        step = np.zeros(3)
        step[i] = h
        numeric[:, i] = (so3_log(base_t @ so3_exp(phi + step)) - so3_log(base_t @ so3_exp(phi - step))) / (2 * h)
    assert np.allclose(right_jacobian(phi), numeric, atol=1e-8)


def test_quat_exp_of_is_quat_exp_on_floats():
    for phi in (np.array([0.4, -0.2, 1.3]), np.array([3e-9, 0.0, -1e-9]), np.zeros(3)):
        assert np.array_equal(np.array(quat_exp_of(*phi.tolist())), quat_exp(phi))
        assert np.allclose(rotvec_quat(*phi.tolist()), quat_exp(phi), atol=1e-17)


def test_the_compiled_primitives_are_bit_for_bit_the_interpreted_ones():
    """The kernels call the numba forms; the per-sample paths the plain ones: the same numbers, to the last
    bit, from both (including the small-angle branches)."""
    from vtolpose.estimator.core import rotation

    local = np.random.default_rng(11)
    for scale in (1.0, 1e-5, 1e-9, 0.0):
        a, b = random_quats(2)
        phi = local.normal(size=3) * scale
        cases = [(rotation.quat_product, (*a, *b)), (rotation.rotate, (*a, *phi)), (rotation.rot_of, tuple(a)),
                 (rotation.rotvec_quat, tuple(phi)), (rotation.quat_exp_of, tuple(phi)),
                 (rotation.right_jacobian_of, tuple(phi))]
        for plain, args in cases:
            args = tuple(float(x) for x in args)
            compiled = getattr(rotation, "compiled_" + plain.__name__)
            assert np.array_equal(np.array(compiled(*args)), np.array(plain(*args))), plain.__name__


def test_importing_the_rotations_loads_no_numba():
    from test_layout import printed_by_a_fresh_process

    assert printed_by_a_fresh_process("import sys, vtolpose.estimator.core.rotation; print('numba' in sys.modules)") == "False"


def test_yaw_of_is_the_yaw_of_the_euler_angles_to_the_bit():
    """``yaw_of`` takes only the two entries of R it needs: the same numbers and shapes as the Euler angles' yaw,
    for one quaternion, a stack, and a stack of stacks (the heading hypotheses, the filter's state)."""
    rng = np.random.default_rng(11)
    q = rng.normal(size=(4000, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    for qs in (q, q.reshape(40, 100, 4), q[7], q[:1]):
        yaw, reference = yaw_of(qs), euler_from_quat(qs)[..., 2]
        assert yaw.shape == reference.shape and np.array_equal(yaw, reference)
    assert yaw_of([1.0, 0.0, 0.0, 0.0]) == 0.0 and isinstance(yaw_of(q[0]), np.ndarray)
