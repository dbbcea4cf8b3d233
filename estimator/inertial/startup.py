"""Building the first filter state: from a still start, or from an in-motion alignment."""

from __future__ import annotations

import numpy as np

from vtolpose.estimator.inertial.initializer import InitialAttitude, InitOptions
from vtolpose.estimator.inertial.motion_alignment import MotionAlignment
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
    until the in-motion alignment places it.
    """
    n = layout.robot_dim
    cov = np.zeros((n, n))
    sigma_v = opts.sigma_velocity_static if init.static else opts.sigma_velocity_moving
    cov[0:3, 0:3] = np.eye(3) * 0.01**2
    cov[3:6, 3:6] = np.eye(3) * sigma_v**2
    cov[6:9, 6:9] = np.diag([init.sigma_roll_pitch**2, init.sigma_roll_pitch**2, sigma_yaw**2])
    if layout.estimates_biases:
        cov[9:12, 9:12] = np.eye(3) * init.sigma_gyro_bias**2
        R = quat_to_rot(init.q)
        down_b = R.T @ np.array([0.0, 0.0, 1.0])
        along = np.outer(down_b, down_b)
        absorbed = init.static and opts.estimate_gravity
        sigma_along = 0.1 * opts.sigma_accel_bias if absorbed else opts.sigma_accel_bias
        P_ba = opts.sigma_accel_bias**2 * (np.eye(3) - along) + sigma_along**2 * along
        if init.static:
            A = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]) @ R / init.gravity
            cov[6:9, 6:9] += A @ P_ba @ A.T
            cov[6:9, 12:15] = A @ P_ba
            cov[12:15, 6:9] = cov[6:9, 12:15].T
        cov[12:15, 12:15] = P_ba
    return cov


def state_from_static(layout: StateLayout, init: InitialAttitude, opts: InitOptions, sigma_yaw: float) -> FilterState:
    state = FilterState(layout)
    state.t_ns = init.t_ns
    state.q = init.q
    state.b_g = init.gyro_bias.copy()
    state.cov = initial_covariance(layout, init, opts, sigma_yaw)
    return state


def state_from_alignment(layout: StateLayout, alignment: MotionAlignment) -> FilterState:
    """Pose, velocity and biases from the fit, with its covariance."""
    state = FilterState(layout)
    state.t_ns = alignment.t_ns
    state.p, state.v, state.q = alignment.p.copy(), alignment.v.copy(), alignment.q.copy()
    state.b_g = alignment.gyro_bias.copy()
    if layout.estimates_biases:
        state.b_a = alignment.accel_bias.copy()
    n = layout.robot_dim
    state.cov = alignment.cov[:n, :n].copy()
    return state
