"""The NED/FRD → ENU/FLU edge (REP 103): poses, and covariances checked against perturbed poses."""

import numpy as np

from vtolpose.estimator.core import frames
from vtolpose.estimator.core.rotation import quat_conj, quat_exp, quat_log, quat_mul, quat_normalize, quat_to_rot

rng = np.random.default_rng(11)


def numeric_jacobian(f, x0: np.ndarray, h: float = 1e-6) -> np.ndarray:
    cols = [(f(x0 + h * e) - f(x0 - h * e)) / (2 * h) for e in np.eye(len(x0))]
    return np.column_stack(cols)


def test_pose_round_trip_and_axes():
    p = rng.normal(size=(20, 3))
    q = quat_normalize(rng.normal(size=(20, 4)))
    p_enu, q_enu = frames.pose_ned_frd_to_enu_flu(p, q)
    assert np.allclose(p_enu[:, 0], p[:, 1]) and np.allclose(p_enu[:, 2], -p[:, 2])
    back_p, back_q = frames.pose_enu_flu_to_ned_frd(p_enu, q_enu)
    assert np.allclose(back_p, p) and np.allclose(back_q, q)
    # Level, nose north (identity in NED/FRD) is yaw +90° in ENU/FLU: the body's x points along ENU's y.
    _, q_level = frames.pose_ned_frd_to_enu_flu(np.zeros(3), np.array([1.0, 0, 0, 0]))
    assert np.allclose(quat_to_rot(q_level) @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(quat_to_rot(q_level) @ [0, 0, 1], [0, 0, 1])  # FLU up is ENU up


def test_pose_covariance_follows_the_perturbed_pose():
    """The covariance map is the Jacobian of 'perturb in NED, convert, read the error in ENU'."""
    p0, q0 = rng.normal(size=3), quat_normalize(rng.normal(size=4))
    p0_enu, q0_enu = frames.pose_ned_frd_to_enu_flu(p0, q0)

    def error_enu(dx: np.ndarray) -> np.ndarray:
        q_true = quat_mul(quat_exp(dx[3:]), q0)  # R_true = Exp(δθ) R, the estimator's convention
        p_enu, q_enu = frames.pose_ned_frd_to_enu_flu(p0 + dx[:3], q_true)
        return np.concatenate([p_enu - p0_enu, quat_log(quat_mul(q_enu, quat_conj(q0_enu)))])

    jac = numeric_jacobian(error_enu, np.zeros(6))
    a = rng.normal(size=(6, 6))
    cov = a @ a.T
    assert np.allclose(frames.pose_covariance_ned_to_enu(cov), jac @ cov @ jac.T, atol=1e-6)
    # a finite rotation error maps exactly, not only to first order
    dx = np.r_[0.3, -1.0, 2.0, 0.4, -0.2, 0.9]
    assert np.allclose(error_enu(dx), np.r_[frames.R_ENU_NED @ dx[:3], frames.R_ENU_NED @ dx[3:]])


def test_twist_covariance_follows_body_vectors():
    v_frd = rng.normal(size=6)
    jac = numeric_jacobian(lambda x: np.concatenate([frames.frd_to_flu(x[:3]), frames.frd_to_flu(x[3:])]), v_frd)
    a = rng.normal(size=(6, 6))
    cov = a @ a.T
    out = frames.body_covariance_frd_to_flu(cov)
    assert np.allclose(out, jac @ cov @ jac.T)
    assert np.allclose(np.diag(out), np.diag(cov))  # a half turn only flips signs of cross terms
    stacked = frames.pose_covariance_ned_to_enu(np.stack([cov, 2 * cov]))
    assert np.allclose(stacked[1], 2 * frames.pose_covariance_ned_to_enu(cov))
