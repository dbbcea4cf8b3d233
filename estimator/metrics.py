"""Scores of an estimated trajectory against truth, and filter-consistency (NEES) helpers.

Pure and vectorised. The estimate is interpolated at the truth times (linear position, slerp
attitude), never the other way round, so the truth is never smoothed. Truth tracks a body point
``point_b`` (the Leica prism, a mocap marker), so the estimate is moved to that point with its
own attitude before comparing. No alignment is applied: estimate and truth share the NED frame.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from vtolpose.estimator.core.chi2 import upper_quantile
from vtolpose.estimator.core.covariance import P
from vtolpose.estimator.core.rotation import quat_conj, quat_log, quat_mul, quat_slerp, quat_to_rot, rotation_angle, skew


class Trajectory(Protocol):
    """Anything with ``t_ns`` (N,), ``p`` (N, 3) and ``q`` (N, 4) or None, e.g. ``TruthSeries``."""

    t_ns: np.ndarray
    p: np.ndarray
    q: np.ndarray | None


class Fixes(Protocol):
    """Anything with ``t_ns`` (N,) and ``p_ned`` (N, 3), e.g. ``GpsSeries``."""

    t_ns: np.ndarray
    p_ned: np.ndarray


def interpolate_poses(
    t_query: np.ndarray, t_ns: np.ndarray, p: np.ndarray, q: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Poses at ``t_query`` (inside ``[t_ns[0], t_ns[-1]]``): linear in position, slerp in attitude."""
    t_query = np.asarray(t_query, dtype=np.int64)
    t_ns = np.asarray(t_ns, dtype=np.int64)
    p = np.asarray(p, dtype=float)
    if t_ns.size < 2:
        i = np.zeros(t_query.shape, dtype=int)
        return p[i], None if q is None else np.asarray(q, dtype=float)[i]
    i = np.clip(np.searchsorted(t_ns, t_query, side="right") - 1, 0, t_ns.size - 2)
    # Differences in int64 first: float64 of absolute times would lose ~100 ns.
    alpha = (t_query - t_ns[i]).astype(float) / (t_ns[i + 1] - t_ns[i]).astype(float)
    p_i = p[i] + alpha[:, None] * (p[i + 1] - p[i])
    if q is None:
        return p_i, None
    q = np.asarray(q, dtype=float)
    return p_i, quat_slerp(q[i], q[i + 1], alpha)


def evaluate(
    est_t_ns: np.ndarray,
    est_p: np.ndarray,
    est_q: np.ndarray | None,
    truth: Trajectory,
    point_b: np.ndarray | None = None,
) -> dict:
    """Position/attitude RMSE, drift and maximum error of an estimate over the truth inside its span.

    ``point_b`` is the body point the truth positions track (zero: the IMU). ``est_q`` may be
    None only when that point is the origin and the truth has no attitude.
    Raises ValueError when no truth sample lies inside the estimate's time span.
    """
    est_t_ns = np.asarray(est_t_ns, dtype=np.int64)
    point_b = np.zeros(3) if point_b is None else np.asarray(point_b, dtype=float).reshape(3)
    if est_q is None and (np.any(point_b != 0.0) or truth.q is not None):
        raise ValueError("evaluate: the estimate needs attitude to reach point_b or to score attitude")
    if est_t_ns.size == 0 or np.any(np.diff(est_t_ns) <= 0):
        raise ValueError("evaluate: estimate times must be non-empty and strictly increasing")
    inside = (truth.t_ns >= est_t_ns[0]) & (truth.t_ns <= est_t_ns[-1])
    if not np.any(inside):
        raise ValueError(
            f"evaluate: no truth sample inside the estimate's span [{est_t_ns[0]}, {est_t_ns[-1]}] ns "
            f"(truth spans [{truth.t_ns[0]}, {truth.t_ns[-1]}] ns)"
        )
    t = truth.t_ns[inside]
    p_true = np.asarray(truth.p, dtype=float)[inside]
    p_est, q_est = interpolate_poses(t, est_t_ns, est_p, est_q)
    if q_est is not None:
        p_est = p_est + quat_to_rot(q_est) @ point_b
    err = p_est - p_true
    dist = np.linalg.norm(err, axis=1)
    travelled = float(np.sum(np.linalg.norm(np.diff(p_true, axis=0), axis=1)))
    result = {
        "samples": int(t.size),
        "truth_samples_outside_estimate": int(np.sum(~inside)),
        "t_start_ns": int(t[0]),
        "t_end_ns": int(t[-1]),
        "duration_s": float((t[-1] - t[0]) * 1e-9),
        "position_rmse_m": float(np.sqrt(np.mean(dist**2))),
        "position_rmse_ned_m": np.sqrt(np.mean(err**2, axis=0)).tolist(),
        "max_position_error_m": float(np.max(dist)),
        "final_drift_m": float(dist[-1]),
        "distance_travelled_m": travelled,
        "drift_percent": float(100.0 * dist[-1] / travelled) if travelled > 0.0 else None,
        "attitude_rmse_deg": None,
        "max_attitude_error_deg": None,
    }
    if truth.q is not None:
        angle = np.degrees(rotation_angle(np.asarray(truth.q, dtype=float)[inside], q_est))
        result["attitude_rmse_deg"] = float(np.sqrt(np.mean(angle**2)))
        result["max_attitude_error_deg"] = float(np.max(angle))
    return result


def gps_error_rmse(gps: Fixes, truth: Trajectory, lever_arm_b: np.ndarray, point_b: np.ndarray) -> dict:
    """RMSE of raw GPS fixes against the antenna position predicted from truth, at the GPS times.

    With truth attitude the antenna is ``p − R point_b + R lever_arm``. Without it the fixes are
    compared with the truth positions directly, which is exact only when the antenna *is* the
    truth point (as in the EuRoC import, where the "GPS" is the Leica prism); the result then
    carries a ``note`` with the distance between the two points.
    """
    lever_arm_b = np.asarray(lever_arm_b, dtype=float).reshape(3)
    point_b = np.asarray(point_b, dtype=float).reshape(3)
    inside = (gps.t_ns >= truth.t_ns[0]) & (gps.t_ns <= truth.t_ns[-1])
    if not np.any(inside):
        raise ValueError("gps_error_rmse: no GPS fix inside the truth's time span")
    p_true, q_true = interpolate_poses(gps.t_ns[inside], truth.t_ns, truth.p, truth.q)
    result: dict = {}
    if q_true is not None:
        p_true = p_true + quat_to_rot(q_true) @ (lever_arm_b - point_b)
    elif not np.allclose(lever_arm_b, point_b, atol=1e-6):
        result["note"] = (
            "truth has no attitude: fixes compared with the truth point directly, although the antenna "
            f"is {np.linalg.norm(lever_arm_b - point_b):.3f} m from it"
        )
    err = np.asarray(gps.p_ned, dtype=float)[inside] - p_true
    result.update(
        samples=int(np.sum(inside)),
        rmse_m=float(np.sqrt(np.mean(np.sum(err**2, axis=1)))),
        rmse_ned_m=np.sqrt(np.mean(err**2, axis=0)).tolist(),
    )
    return result


def nees(err: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Normalised estimation error squared ``eᵀ P⁻¹ e`` for stacks ``err[..., n]``, ``cov[..., n, n]``."""
    err = np.asarray(err, dtype=float)
    solved = np.linalg.solve(np.asarray(cov, dtype=float), err[..., None])[..., 0]
    return np.sum(err * solved, axis=-1)


def chi2_band(dof: int, prob: float = 0.95, n_samples: int = 1) -> tuple[float, float]:
    """Two-sided ``prob`` band of the mean of ``n_samples`` independent NEES values of ``dof``.

    ``n_samples = 1`` is the per-sample band; a consistent filter's NEES falls inside it with
    probability ``prob``, and its NEES mean ≈ dof.
    """
    tail = 0.5 * (1.0 - prob)
    k = dof * n_samples
    return upper_quantile(k, 1.0 - tail) / n_samples, upper_quantile(k, tail) / n_samples


def nees_summary(values: np.ndarray, dof: int, prob: float = 0.95) -> dict:
    """Mean NEES, its per-sample band, and the fraction of samples inside that band (≈ prob if consistent)."""
    values = np.asarray(values, dtype=float)
    lo, hi = chi2_band(dof, prob)
    return {
        "dof": int(dof),
        "nees_mean": float(np.mean(values)),
        "band_per_sample": [lo, hi],
        "mean_in_band": bool(lo <= np.mean(values) <= hi),
        "fraction_in_band": float(np.mean((values >= lo) & (values <= hi))),
        "samples": int(values.size),
    }



def pose_errors_for_nees(
    t_ns: np.ndarray, p: np.ndarray, q: np.ndarray, pose_cov: np.ndarray, truth: Trajectory, point_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int]:
    """Errors and covariances of the filter's pose samples against truth, for NEES.

    The filter's pose covariance is over ``[δp, δθ]`` with ``R_true = Exp(δθ) R_est``. The
    error of the tracked point ``p + R point_b`` is ``δp − [R point_b]× δθ``; with truth
    attitude the error is 6-dof ``[point error, Log(R_true R_estᵀ)]``, without it 3-dof.
    Samples outside the truth's span are dropped.
    """
    point_b = np.asarray(point_b, dtype=float).reshape(3)
    inside = (t_ns >= truth.t_ns[0]) & (t_ns <= truth.t_ns[-1])
    t_ns, p, q, pose_cov = t_ns[inside], p[inside], q[inside], pose_cov[inside]
    p_true, q_true = interpolate_poses(t_ns, truth.t_ns, truth.p, truth.q)
    R = quat_to_rot(q)
    lever_w = R @ point_b
    J = np.zeros((len(t_ns), 6, 6))
    J[:, 0:3, 0:3] = np.eye(3)
    J[:, 0:3, 3:6] = -skew(lever_w) if len(t_ns) else 0.0
    J[:, 3:6, 3:6] = np.eye(3)
    cov = J @ pose_cov @ np.swapaxes(J, 1, 2)
    err_p = p_true - (p + lever_w)
    if q_true is None:
        return err_p, cov[:, P, P], 3
    err_th = quat_log(quat_mul(q_true, quat_conj(q)))
    return np.hstack([err_p, err_th]), cov, 6


def rigid_alignment(p_est: np.ndarray, p_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation (no scale) that put ``p_est`` best onto ``p_true`` (Horn/Umeyama):
    ``p_true ≈ R p_est + t`` in the least-squares sense."""
    p_est, p_true = np.asarray(p_est, dtype=float), np.asarray(p_true, dtype=float)
    mean_e, mean_t = p_est.mean(axis=0), p_true.mean(axis=0)
    u, _, vt = np.linalg.svd((p_true - mean_t).T @ (p_est - mean_e))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    R = u @ d @ vt
    return R, mean_t - R @ mean_e


def motion_onset(truth: Trajectory, speed_mps: float = 0.1, window_s: float = 1.0) -> int | None:
    """First truth time [ns] at which the mean horizontal speed over ``window_s`` exceeds ``speed_mps``
    (the vehicle starts to move: only horizontal motion can show a heading). None if it never does."""
    t = np.asarray(truth.t_ns, dtype=np.int64)
    p = np.asarray(truth.p, dtype=float)
    end = np.searchsorted(t, t + int(window_s * 1e9))
    ok = end < len(t)
    if not np.any(ok):
        return None
    start = np.flatnonzero(ok)
    span = (t[end[ok]] - t[start]) * 1e-9
    speed = np.linalg.norm(p[end[ok], :2] - p[start, :2], axis=1) / span
    moving = np.flatnonzero(speed > speed_mps)
    return int(t[start[moving[0]]]) if len(moving) else None


def mean_world_rotation(q_est: np.ndarray, q_true: np.ndarray) -> np.ndarray:
    """The constant world-frame rotation ``C`` with ``R_true ≈ C R_est`` (chordal least squares).

    A truth given in a motion-capture frame whose "up" is not exactly the local vertical (a
    fraction of a degree is common) differs from any gravity-levelled estimate by such a
    rotation; scoring the error that varies with time removes it.
    """
    m = np.einsum("nij,nkj->ik", quat_to_rot(q_true), quat_to_rot(q_est))
    u, _, vt = np.linalg.svd(m)
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
