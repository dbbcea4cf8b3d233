"""Building the first filter state from the IMU window the start was judged on, and the GPS before it."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from vtolpose.estimator.core.covariance import BA, BG, P, TH, V
from vtolpose.estimator.core.measurements import GpsFix
from vtolpose.estimator.gnss.gps_update import gps_sigmas
from vtolpose.estimator.inertial.initializer import InitialAttitude, InitOptions
from vtolpose.estimator.core.rotation import quat_to_rot
from vtolpose.estimator.core.state import FilterState, StateLayout


def initial_covariance(layout: StateLayout, init: InitialAttitude, opts: InitOptions, sigma_yaw: float) -> np.ndarray:
    """Robot covariance after a still (or accelerometer-only) start.

    Roll and pitch come from the mean specific force, which includes the bias ``b_a``: a
    tilt error ``δθ`` and the bias are one unknown, ``[δθ]× g_W = −R b_a``. The prior says so
    (``δθ = A b_a``) instead of treating them as independent, which would let the first GPS
    accelerations "confirm" a wrong tilt. When g was taken from the same window, the bias
    component along gravity is already absorbed and gets a small variance. ``sigma_yaw`` is
    zero when the heading is unknown: the filter then works in a frame of arbitrary yaw
    until the heading bank places it.
    """
    n = layout.robot_dim
    cov = np.zeros((n, n))
    sigma_v = opts.sigma_velocity_static if init.static else opts.sigma_velocity_moving
    cov[P, P] = np.eye(3) * 0.01**2
    cov[V, V] = np.eye(3) * sigma_v**2
    cov[TH, TH] = np.diag([init.sigma_roll_pitch**2, init.sigma_roll_pitch**2, sigma_yaw**2])
    if layout.estimates_biases:
        cov[BG, BG] = np.eye(3) * init.sigma_gyro_bias**2
        R = quat_to_rot(init.q)
        down_b = R.T @ np.array([0.0, 0.0, 1.0])
        along = np.outer(down_b, down_b)
        absorbed = init.static and opts.estimate_gravity
        sigma_along = 0.1 * opts.sigma_accel_bias if absorbed else opts.sigma_accel_bias
        P_ba = opts.sigma_accel_bias**2 * (np.eye(3) - along) + sigma_along**2 * along
        if init.static:
            A = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]) @ R / init.gravity
            cov[TH, TH] += A @ P_ba @ A.T
            cov[TH, BA] = A @ P_ba
            cov[BA, TH] = cov[TH, BA].T
        cov[BA, BA] = P_ba
    return cov


def state_from_static(layout: StateLayout, init: InitialAttitude, opts: InitOptions, sigma_yaw: float) -> FilterState:
    state = FilterState(layout)
    state.t_ns = init.t_ns
    state.q = init.q
    state.b_g = init.gyro_bias.copy()
    state.cov = initial_covariance(layout, init, opts, sigma_yaw)
    return state


def velocity_from_fixes(fixes: Sequence[GpsFix], t_ns: int, sigma_floor_m: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Velocity at ``t_ns`` and its covariance from the fixes before it (at least 5 over at least 0.3 s):
    a least-squares fit of position, velocity and a constant acceleration per axis, weighted by the
    fixes' sigmas, its covariance scaled up by the fit's residuals when the motion was not that
    smooth (a vehicle carried by hand). What the IMU cannot tell — rest from steady straight flight,
    or from a steady turn — the GPS can. None when the fixes are too few."""
    fixes = [f for f in fixes if f.t_ns <= t_ns]
    if len(fixes) < 5 or (fixes[-1].t_ns - fixes[0].t_ns) * 1e-9 < 0.3:
        return None
    tau = np.array([(f.t_ns - t_ns) * 1e-9 for f in fixes])
    design = np.column_stack([np.ones_like(tau), tau, 0.5 * tau**2])
    v, var = np.zeros(3), np.zeros(3)
    for axis in range(3):
        sigma = np.array([gps_sigmas(f, sigma_floor_m)[0 if axis < 2 else 1] for f in fixes])
        a = design / sigma[:, None]
        y = np.array([f.p_ned[axis] for f in fixes]) / sigma
        normal_inv = np.linalg.inv(a.T @ a)
        x = normal_inv @ a.T @ y
        reduced_chi2 = float(np.sum((y - a @ x) ** 2)) / (len(fixes) - 3)
        v[axis] = x[1]
        var[axis] = normal_inv[1, 1] * max(1.0, reduced_chi2)
    return v, np.diag(var)


def mean_acceleration_from_fixes(fixes: Sequence[GpsFix], t0_ns: int, t1_ns: int, fit_s: float,
                                 sigma_floor_m: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The mean acceleration over ``[t0, t1]`` and its covariance: the change of the velocity the fixes give at
    either end (each from the fixes of the ``fit_s`` before it), over the time between. None when the fixes
    cannot give both velocities."""
    ends = []
    for t_ns in (t0_ns, t1_ns):
        near = [f for f in fixes if 0 <= t_ns - f.t_ns < fit_s * 1e9]
        fitted = velocity_from_fixes(near, t_ns, sigma_floor_m)
        if fitted is None:
            return None
        ends.append(fitted)
    span = (t1_ns - t0_ns) * 1e-9
    (v0, c0), (v1, c1) = ends
    return (v1 - v0) / span, (c0 + c1) / span**2


def tilt_sigma_of_mean_acceleration(accel: np.ndarray, cov: np.ndarray, gravity: float) -> float:
    """The sigma of a tilt taken from a mean specific force whose window held a mean acceleration ``accel``
    (covariance ``cov``): its horizontal part turns the sensed gravity by ``|a_h| / g``, in a direction the
    start cannot know without the heading, so each axis gets all of it."""
    return float(np.sqrt(accel[:2] @ accel[:2] + np.trace(cov[:2, :2]))) / gravity
