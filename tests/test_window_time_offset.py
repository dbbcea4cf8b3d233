"""The camera's time offset solved in the visual-inertial window: its Jacobian, its recovery, its hand-over.

A synthetic book flight (tests/test_visual_inertial.py's frames: ground points projected from the true
pose) whose frames are stamped 10 ms late: each frame shows the pose of 10 ms before its stamp, the
residual offset to find is −10 ms, as in ``vtolpose bench --only camera-clock``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import central_difference
from test_visual_inertial import CAMERA, SyntheticCamera
from vtolpose.drivers.simulator import SimulationOptions, simulate_flight
from vtolpose.estimator.core.rotation import quat_to_rot
from vtolpose.estimator.core.state import CalibrationLayout, FilterState, StateLayout
from vtolpose.estimator.inertial.imu_delta import ImuDownsampler
from vtolpose.estimator.inertial.initializer import InitOptions
from vtolpose.estimator.init.visual_inertial import Gauge, VisualInertialInitializer, VisualInertialStart
from vtolpose.estimator.init.window_solver import Layout, _Estimate, _Residuals, solve_window, tangent_basis
from vtolpose.estimator.start import StartCoordinator
from vtolpose.estimator.vision.time_offset import TimeOffsetEstimate, TimeOffsetOptions

LATE_S = 0.010  # each frame stamped this late: the residual offset is −LATE_S
PRIOR_SIGMA_S = 0.010


@pytest.fixture(scope="module")
def flight():
    return simulate_flight("book", 6.0, 3, SimulationOptions(start_s=20.0))


@pytest.fixture(scope="module")
def solved(flight):
    """The initializer and the start of the late frames, the offset solved from a 10 ms prior."""
    return start_from_late_frames(flight, LATE_S, PRIOR_SIGMA_S)


def start_from_late_frames(flight, late_s: float, prior_sigma_s: float) -> tuple[VisualInertialInitializer, VisualInertialStart | None]:
    """Feed the IMU and frames stamped ``late_s`` after the instant they show; the start, or None."""
    init = VisualInertialInitializer(CAMERA, flight.calibration.imu.noise, flight.calibration.imu.gravity, 1.0)
    if prior_sigma_s:
        init.set_time_offset_prior(0.0, prior_sigma_s)
    camera = SyntheticCamera(flight, 0.5, span_m=2.0)
    downsampler = ImuDownsampler(100.0)
    t_first = int(flight.imu.t_ns[0])
    stamps = t_first + 100_000_000 + np.round(np.arange(0.0, 6.0, 1.0 / CAMERA.rate_hz) * 1e9).astype(np.int64)
    f = 0
    for i, t in enumerate(flight.imu.t_ns.tolist()):
        while f < len(stamps) and stamps[f] <= t:
            for delta in (downsampler.flush(), downsampler.hold(int(stamps[f]))):
                if delta is not None:
                    init.add_delta(delta)
            seen = camera.frame(int(stamps[f]) - int(round(late_s * 1e9)))
            start = init.add_frame(dataclasses.replace(seen, t_ns=int(stamps[f])), Gauge(np.zeros(3), 0.0))
            if start is not None:
                return init, start
            f += 1
        if f >= len(stamps):
            break
        delta = downsampler.add(t, flight.imu.gyro[i], flight.imu.accel[i])
        if delta is not None:
            init.add_delta(delta)
    return init, None


def errors(flight, start: VisualInertialStart) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Body-frame velocity error and gravity's direction error in the body (both free of the heading gauge), and
    the start's sigmas."""
    t_s = (start.t_ns - int(flight.imu.t_ns[0])) * 1e-9
    truth = flight.trajectory.kinematics(np.array([t_s]))
    R, R_true = quat_to_rot(start.q), truth.rotation()[0]
    v_err = R.T @ start.v - R_true.T @ truth.v[0]
    down_err = R.T @ np.array([0.0, 0.0, 1.0]) - R_true.T @ np.array([0.0, 0.0, 1.0])
    return v_err, down_err, np.sqrt(np.diag(start.cov))


def test_a_window_solved_with_a_wrong_offset_is_bent_by_it(flight):
    """The cause: solved with the configured offset taken as exact, 10 ms wrong puts the velocity and the tilt
    several sigmas off, where the right offset leaves them inside theirs."""
    _, right = start_from_late_frames(flight, 0.0, 0.0)
    _, wrong = start_from_late_frames(flight, LATE_S, 0.0)
    assert right is not None and wrong is not None and wrong.time_offset_s is None
    v_right, _, sd_right = errors(flight, right)
    v_wrong, down_wrong, sd_wrong = errors(flight, wrong)
    assert np.all(np.abs(v_right) < 3.0 * sd_right[3:6])
    assert np.max(np.abs(v_wrong) / sd_wrong[3:6]) > 4.0
    assert np.max(np.abs(down_wrong[:2]) / sd_wrong[6:8]) > 2.0


def test_the_window_finds_the_offset_and_the_state_it_bent(flight, solved):
    _, start = solved
    assert start is not None and start.time_offset_s is not None
    v_err, down_err, sd = errors(flight, start)
    sigma_td = sd[15]
    assert sigma_td < 0.5 * PRIOR_SIGMA_S  # learnt from the window, not the prior
    assert abs(start.time_offset_s + LATE_S) < 2.0 * sigma_td, (start.time_offset_s, sigma_td)
    assert np.all(np.abs(v_err) < 3.0 * sd[3:6])
    assert np.all(np.abs(down_err[:2]) < 3.0 * sd[6:8])
    # The offset sits between the robot and the landmarks, correlated with both: what it learns moves them.
    n = len(start.cov)
    assert n == 15 + 1 + 6 * len(start.landmarks)
    corr = start.cov[15] / np.sqrt(np.diag(start.cov) * start.cov[15, 15])
    assert np.max(np.abs(corr[3:6])) > 0.1 and np.max(np.abs(corr[16:])) > 0.05
    assert np.linalg.eigvalsh(start.cov).min() > -1e-12 * np.abs(start.cov).max()


def test_pixel_jacobians_with_the_offset_match_central_differences(solved):
    init, start = solved
    assert start is not None
    problem, _, _ = init._problem(init._usable_frames())
    solution = solve_window(problem)
    lay = Layout.of(problem)
    assert lay.time_offset and lay.TD.stop - lay.TD.start == 1
    est = _Estimate(solution.gravity_dir, solution.bias_g, solution.bias_a, solution.p, solution.v, solution.points,
                    -0.008)
    model = _Residuals(problem, np.ones(len(problem.obs_frame), dtype=bool))
    tangent = tangent_basis(est.g_dir)
    lin = model.evaluate(est, tangent)
    obs = np.arange(0, len(lin.frame), 7)  # a sample of the observations keeps the differences quick
    analytic = np.zeros((len(obs), 2, lay.size))
    for row, n in enumerate(obs):
        k, j = lin.frame[n], lin.point[n]
        analytic[row, :, lay.BG] = lin.J_bg[n]
        if k >= 1:
            analytic[row, :, lay.p(k)] = lin.J_p[n]
        analytic[row, :, lay.v(k)] = lin.J_v[n]
        analytic[row, :, lay.TD] = lin.J_td[n]
        analytic[row, :, lay.point(j)] = lin.J_f[n]

    def pixels(dx: np.ndarray) -> np.ndarray:
        return model.evaluate(est.moved(dx, lay, tangent), tangent, jacobian=False).r_pix[obs]

    numeric = central_difference(pixels, np.zeros(lay.size), 1e-6)
    columns = np.r_[lay.BG.start : lay.BG.stop, lay.p(1).start : lay.size]  # all but gravity and b_a (no pixel rows)
    scale = np.abs(numeric[..., columns]).max()
    np.testing.assert_allclose(analytic[..., columns], numeric[..., columns], atol=2e-4 * scale)
    assert np.abs(analytic[..., lay.TD]).max() > 1e-3 * scale  # the offset's column is not vacuous


def test_the_filter_starts_with_the_offset_state_the_window_solved(solved):
    _, start = solved
    assert start is not None
    built = coordinator().from_window(start).state
    assert isinstance(built, FilterState)
    assert built.calib.tolist() == [start.time_offset_s] and built.calib_layout == CalibrationLayout(time_offset=True)
    assert built.map_start == built.robot_dim + 1 and built.n_landmarks == len(start.landmarks)
    np.testing.assert_array_equal(built.cov, start.cov)  # the window's joint covariance, offset row included


def coordinator() -> StartCoordinator:
    """The filter's start coordinator (biases estimated, no heading known, no camera initializer of its own)."""
    return StartCoordinator(StateLayout("biases"), InitOptions(), 9.81, None, 0.035, 0.02, None)


def test_the_filter_reads_the_offset_a_start_brought_and_keeps_its_correlations(solved):
    _, start = solved
    state = coordinator().from_window(start).state
    before = state.cov.copy()
    clock = TimeOffsetEstimate(TimeOffsetOptions(estimate=True, sigma_s=PRIOR_SIGMA_S))
    clock.attach(state)  # what the camera pipeline does before each frame: the start's state is kept
    np.testing.assert_array_equal(state.cov, before)
    value, sigma = clock.reading(state)
    assert value == start.time_offset_s and sigma == pytest.approx(np.sqrt(start.cov[15, 15]))
