"""Trajectory scores and NEES helpers: known errors give known numbers."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from vtolpose.estimator.metrics import (
    chi2_band, evaluate, gps_error_rmse, interpolate_poses, mean_world_rotation, motion_onset, nees, nees_summary,
    pose_errors_for_nees, rigid_alignment,
)
from vtolpose.estimator.core.rotation import quat_exp, quat_from_euler, quat_mul, quat_to_rot, rotation_angle

S = 1_000_000_000


def truth(t_ns, p, q=None):
    return SimpleNamespace(t_ns=np.asarray(t_ns, dtype=np.int64), p=np.asarray(p, dtype=float), q=q)


def yaw_quats(yaw: np.ndarray) -> np.ndarray:
    return quat_exp(np.column_stack([np.zeros_like(yaw), np.zeros_like(yaw), yaw]))


def test_constant_offset_gives_known_scores() -> None:
    t = np.arange(11, dtype=np.int64) * S
    p_true = np.column_stack([np.arange(11.0), np.zeros(11), np.zeros(11)])  # 10 m straight north
    q = np.tile([1.0, 0, 0, 0], (11, 1))
    r = evaluate(t, p_true + [0.3, 0.4, 0.0], q, truth(t, p_true, q))
    assert r["position_rmse_m"] == pytest.approx(0.5)
    assert r["max_position_error_m"] == pytest.approx(0.5)
    assert r["final_drift_m"] == pytest.approx(0.5)
    assert r["distance_travelled_m"] == pytest.approx(10.0)
    assert r["drift_percent"] == pytest.approx(5.0)
    assert r["position_rmse_ned_m"] == pytest.approx([0.3, 0.4, 0.0])
    assert r["attitude_rmse_deg"] == pytest.approx(0.0, abs=1e-6)
    assert r["samples"] == 11 and r["duration_s"] == pytest.approx(10.0)


def test_growing_error_rmse_and_drift() -> None:
    t = np.arange(4, dtype=np.int64) * S
    p_true = np.zeros((4, 3))
    p_est = np.column_stack([[0.0, 1.0, 2.0, 3.0], np.zeros(4), np.zeros(4)])
    r = evaluate(t, p_est, np.tile([1.0, 0, 0, 0], (4, 1)), truth(t, p_true))
    assert r["position_rmse_m"] == pytest.approx(np.sqrt((0 + 1 + 4 + 9) / 4))
    assert r["final_drift_m"] == pytest.approx(3.0) and r["max_position_error_m"] == pytest.approx(3.0)
    assert r["drift_percent"] is None and r["attitude_rmse_deg"] is None


def test_estimate_is_interpolated_linearly_and_by_slerp() -> None:
    t_est = np.arange(0, 11, dtype=np.int64) * S
    yaw_est = 0.3 * np.arange(11.0)
    p_est = np.column_stack([2.0 * np.arange(11.0), np.zeros(11), -np.arange(11.0)])
    t_true = t_est[:-1] + S // 2  # midway between estimate samples
    p_mid, q_mid = interpolate_poses(t_true, t_est, p_est, yaw_quats(yaw_est))
    np.testing.assert_allclose(p_mid[:, 0], 2.0 * (np.arange(10) + 0.5))
    np.testing.assert_allclose(rotation_angle(q_mid, yaw_quats(0.3 * (np.arange(10) + 0.5))), 0.0, atol=1e-9)
    r = evaluate(t_est, p_est, yaw_quats(yaw_est), truth(t_true, p_mid, yaw_quats(0.3 * (np.arange(10) + 0.5))))
    assert r["position_rmse_m"] == pytest.approx(0.0, abs=1e-12)
    assert r["attitude_rmse_deg"] == pytest.approx(0.0, abs=1e-6)


def test_constant_attitude_error_gives_its_angle() -> None:
    t = np.arange(5, dtype=np.int64) * S
    q_true = yaw_quats(np.linspace(0.0, 1.0, 5))
    q_est = quat_mul(q_true, quat_from_euler(np.radians(2.0), 0.0, 0.0))
    r = evaluate(t, np.zeros((5, 3)), q_est, truth(t, np.zeros((5, 3)), q_true))
    assert r["attitude_rmse_deg"] == pytest.approx(2.0)
    assert r["max_attitude_error_deg"] == pytest.approx(2.0)


def test_truth_point_is_reached_with_the_estimated_attitude() -> None:
    t = np.arange(3, dtype=np.int64) * S
    q = yaw_quats(np.full(3, np.pi / 2))  # facing east: body forward = world east
    point_b = np.array([1.0, 0.0, 0.0])
    p_imu = np.zeros((3, 3))
    r = evaluate(t, p_imu, q, truth(t, np.tile([0.0, 1.0, 0.0], (3, 1))), point_b)
    assert r["position_rmse_m"] == pytest.approx(0.0, abs=1e-12)
    r0 = evaluate(t, p_imu, q, truth(t, np.tile([0.0, 1.0, 0.0], (3, 1))))
    assert r0["position_rmse_m"] == pytest.approx(1.0)


def test_only_truth_inside_the_estimate_span_counts() -> None:
    t_est = np.array([2, 5], dtype=np.int64) * S
    t_true = np.arange(8, dtype=np.int64) * S
    r = evaluate(t_est, np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)), truth(t_true, np.zeros((8, 3))))
    assert r["samples"] == 4 and r["truth_samples_outside_estimate"] == 4
    with pytest.raises(ValueError, match="no truth sample inside"):
        evaluate(t_est + 100 * S, np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)), truth(t_true, np.zeros((8, 3))))
    with pytest.raises(ValueError, match="needs attitude"):
        evaluate(t_est, np.zeros((2, 3)), None, truth(t_true, np.zeros((8, 3))), [0.1, 0.0, 0.0])


def test_evaluate_handles_a_long_trajectory() -> None:
    n = 200_000
    t = np.arange(n, dtype=np.int64) * 5_000_000
    rng = np.random.default_rng(0)
    q = quat_exp(rng.normal(size=(n, 3)) * 0.1)
    p = rng.normal(size=(n, 3))
    scores = evaluate(t, p, q, truth(t[::2] + 1, p[::2], q[::2]), [0.0, 0, 0])
    assert scores["samples"] == n // 2 and scores["position_rmse_m"] < 1e-3


def test_nees_of_correct_gaussian_samples_is_dof() -> None:
    rng = np.random.default_rng(7)
    n, dof = 20_000, 6
    a = rng.normal(size=(n, dof, dof))
    cov = a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(dof)
    err = (np.linalg.cholesky(cov) @ rng.normal(size=(n, dof, 1)))[..., 0]
    values = nees(err, cov)
    assert values.shape == (n,)
    assert values.mean() == pytest.approx(dof, abs=4 * np.sqrt(2 * dof / n))
    # An over-confident filter (covariance 4x too small) scores ~4x dof.
    assert nees(err, cov / 4).mean() == pytest.approx(4 * dof, rel=0.05)
    summary = nees_summary(values, dof)
    assert summary["mean_in_band"] and summary["fraction_in_band"] == pytest.approx(0.95, abs=0.01)


def test_nees_single_sample() -> None:
    assert nees(np.array([1.0, 2.0]), np.diag([1.0, 4.0])) == pytest.approx(2.0)


def test_chi2_band_numbers() -> None:
    assert chi2_band(1) == pytest.approx((0.000982, 5.0239), abs=1e-4)
    assert chi2_band(3) == pytest.approx((0.2158, 9.3484), abs=1e-4)
    assert chi2_band(6, 0.99) == pytest.approx((0.6757, 18.5476), abs=1e-4)
    lo, hi = chi2_band(3, 0.95, n_samples=100)  # band of a 100-sample mean: much narrower
    assert 2.5 < lo < 3.0 < hi < 3.5


def test_gps_error_rmse_with_attitude_and_lever_arm() -> None:
    t = np.arange(10, dtype=np.int64) * S
    q = yaw_quats(np.full(10, np.pi / 2))
    point_b, lever = np.array([0.0, 0.0, -0.1]), np.array([1.0, 0.0, 0.0])
    p_truth = np.zeros((10, 3))
    antenna = p_truth + [0.0, 1.0, 0.1]  # R(yaw 90°) (lever − point_b)
    gps = SimpleNamespace(t_ns=t[::2], p_ned=antenna[::2] + [0.03, 0.0, -0.04])
    r = gps_error_rmse(gps, truth(t, p_truth, q), lever, point_b)
    assert r["rmse_m"] == pytest.approx(0.05) and r["samples"] == 5 and "note" not in r


def test_gps_error_rmse_without_attitude_notes_point_mismatch() -> None:
    t = np.arange(10, dtype=np.int64) * S
    gps = SimpleNamespace(t_ns=t, p_ned=np.full((10, 3), [0.0, 0.0, 0.2]))
    same = gps_error_rmse(gps, truth(t, np.zeros((10, 3))), [0.1, 0, 0], [0.1, 0, 0])
    assert same["rmse_m"] == pytest.approx(0.2) and "note" not in same
    other = gps_error_rmse(gps, truth(t, np.zeros((10, 3))), [0.5, 0, 0], [0.1, 0, 0])
    assert "0.400 m" in other["note"]


def test_rigid_alignment_recovers_a_turn_and_a_shift() -> None:
    rng = np.random.default_rng(3)
    p = rng.normal(size=(50, 3)) * 5.0
    R = quat_to_rot(quat_from_euler(0.01, -0.02, 0.7))
    R_found, t_found = rigid_alignment(p, p @ R.T + [1.0, -2.0, 0.5])
    np.testing.assert_allclose(R_found, R, atol=1e-12)
    np.testing.assert_allclose(t_found, [1.0, -2.0, 0.5], atol=1e-12)


def test_mean_world_rotation_is_the_constant_part_of_the_attitude_error() -> None:
    rng = np.random.default_rng(4)
    q_est = quat_exp(rng.normal(size=(200, 3)))
    tilt = quat_from_euler(0.006, -0.008, 0.0)  # a motion-capture "up" half a degree off
    q_true = quat_mul(np.broadcast_to(tilt, (200, 4)), q_est)
    np.testing.assert_allclose(mean_world_rotation(q_est, q_true), quat_to_rot(tilt), atol=1e-12)


def test_motion_onset_is_the_first_second_of_horizontal_motion() -> None:
    t = np.arange(0, 20_000, 50, dtype=np.int64) * 1_000_000  # 20 Hz for 20 s
    s = t * 1e-9
    north = np.where(s > 5.0, 0.3 * (s - 5.0), 0.0)  # still, then 0.3 m/s
    up_only = truth(t, np.column_stack([np.zeros_like(s), np.zeros_like(s), -s]))  # climbing: no onset
    onset = motion_onset(truth(t, np.column_stack([north, np.zeros_like(s), np.zeros_like(s)])))
    assert 4.0 < onset * 1e-9 < 5.0 and motion_onset(up_only) is None  # the window that first shows it starts


def test_the_nees_attitude_error_is_in_the_world_frame() -> None:
    """The filter's attitude error is global, R_true = Exp(δθ) R_est: with the estimate yawed 90° and the truth
    turned a little further about world north, the error is about north (x), not about the body's axis
    that north is at 90° of yaw (−y); a covariance that knows only an error about north finds it consistent."""
    yaw = quat_from_euler(0.0, 0.0, math.pi / 2)
    tilt = 0.02
    q_true = quat_mul(quat_exp(np.array([tilt, 0.0, 0.0])), yaw)
    track = truth([0, S], np.zeros((2, 3)), np.array([q_true, q_true]))
    pose_cov = np.diag([1e-4, 1e-4, 1e-4, 1e-4, 1e-12, 1e-12])
    err, cov, dof = pose_errors_for_nees(np.array([S // 2]), np.zeros((1, 3)), yaw[None], pose_cov[None], track,
                                         np.zeros(3))
    assert dof == 6
    np.testing.assert_allclose(err[0, 3:], [tilt, 0.0, 0.0], atol=1e-12)
    assert nees(err, cov)[0] == pytest.approx(tilt**2 / 1e-4, rel=1e-9)
