"""The flight simulator: exact IMU, sensor rates and noise statistics, scenario envelopes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vtolpose.drivers.simulator import (
    BookScenario,
    GpsErrorModel,
    ImuErrorModel,
    LandfillScenario,
    SimulationOptions,
    simulate_flight,
)
from vtolpose.drivers.simulator.gps_model import gps_errors
from vtolpose.drivers.simulator.imu_model import corrupt_imu
from vtolpose.estimator.core.rotation import euler_from_quat, quat_mul, quat_to_rot, rotation_angle, yaw_of

EPOCH = 1_000_000_000


def _seconds(t_ns: np.ndarray) -> np.ndarray:
    return (t_ns - EPOCH) * 1e-9


def _integrate_rk4(q, p, v, gyro, accel, dt, gravity):
    """RK4 with step 2·dt: samples k, k+1, k+2 are the start, middle and end of each step."""
    g_w = np.array([0.0, 0.0, gravity])

    def rates(q, v, w, f):
        return 0.5 * quat_mul(q, np.array([0.0, *w])), quat_to_rot(q) @ f + g_w

    h = 2.0 * dt
    ps, qs = [p], [q]
    for k in range(0, len(gyro) - 2, 2):
        (w0, w1, w2), (f0, f1, f2) = gyro[k : k + 3], accel[k : k + 3]
        dq1, dv1 = rates(q, v, w0, f0)
        dq2, dv2 = rates(q + 0.5 * h * dq1, v + 0.5 * h * dv1, w1, f1)
        dq3, dv3 = rates(q + 0.5 * h * dq2, v + 0.5 * h * dv2, w1, f1)
        dq4, dv4 = rates(q + h * dq3, v + h * dv3, w2, f2)
        v2, v3, v4 = v + 0.5 * h * dv1, v + 0.5 * h * dv2, v + h * dv3
        p = p + h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
        v = v + h / 6.0 * (dv1 + 2.0 * dv2 + 2.0 * dv3 + dv4)
        q = q + h / 6.0 * (dq1 + 2.0 * dq2 + 2.0 * dq3 + dq4)
        q = q / np.linalg.norm(q)
        ps.append(p)
        qs.append(q)
    return np.array(ps), np.array(qs)


@pytest.mark.parametrize(
    ("scenario", "start_s"),
    [("book", 0.0), ("landfill", 0.0), ("landfill", 70.0)],  # landfill from 70 s: leg, turn, leg
)
def test_noise_free_imu_integrates_back_to_the_truth(scenario, start_s):
    duration = 60.0
    flight = simulate_flight(scenario, start_s + duration + 0.1, 1, SimulationOptions(imu=ImuErrorModel.perfect()))
    first = int(round(start_s * 125))
    window = slice(first, first + int(duration * 125) + 1)
    truth = flight.trajectory.kinematics(_seconds(flight.imu.t_ns[window]))
    q_true = truth.q()
    p, q = _integrate_rk4(
        q_true[0], truth.p[0], truth.v[0], flight.imu.gyro[window], flight.imu.accel[window], 1 / 125, 9.80665
    )
    position_error = np.linalg.norm(p - truth.p[::2], axis=1).max()
    attitude_error_deg = np.degrees(rotation_angle(q, q_true[::2])).max()
    assert position_error < 2e-3
    assert attitude_error_deg < 0.01


@pytest.mark.parametrize("scenario", ["book", "landfill"])
def test_same_seed_gives_identical_arrays_and_other_seeds_differ(scenario):
    a, b, c = (simulate_flight(scenario, 20.0, seed) for seed in (7, 7, 8))
    for series in ("imu", "gps", "truth"):
        for field in dataclasses.fields(getattr(a, series)):
            same = np.array_equal(getattr(getattr(a, series), field.name), getattr(getattr(b, series), field.name))
            assert same, f"{series}.{field.name}"
    assert not np.array_equal(a.imu.gyro, c.imu.gyro)
    assert not np.array_equal(a.imu.accel, c.imu.accel)
    assert not np.array_equal(a.gps.p_ned, c.gps.p_ned)
    assert np.array_equal(a.truth.p, c.truth.p)  # the motion is the scenario's, only noise is seeded


def test_each_sensor_has_its_own_random_stream():
    plain = simulate_flight("landfill", 20.0, 3)
    other_gps = SimulationOptions(gps=GpsErrorModel(sigma_h=5.0, rate_hz=5.0, correlation_time_s=10.0))
    changed = simulate_flight("landfill", 20.0, 3, other_gps)
    assert np.array_equal(plain.imu.gyro, changed.imu.gyro)
    assert np.array_equal(plain.imu.accel, changed.imu.accel)
    # Distinct seeds per stream: with unit scales, the IMU's first draws (the turn-on gyro
    # bias) and the GPS's first draws (the first fix's error) would coincide on a shared seed.
    unit_imu = dataclasses.replace(ImuErrorModel.perfect(), gyro_turn_on_bias_std=1.0)
    unit = simulate_flight("book", 1.0, 3, SimulationOptions(imu=unit_imu, gps=GpsErrorModel(sigma_h=1.0)))
    first_fix_error = unit.gps.p_ned[0] - unit.truth.p[0]
    assert not np.allclose(first_fix_error[:2], unit.truth.bias_g[0, :2], atol=1e-6)


@pytest.mark.parametrize("scenario", ["book", "landfill"])
def test_rates_and_timestamps(scenario):
    flight = simulate_flight(scenario, 12.0, 0)
    for t_ns, rate, count in ((flight.imu.t_ns, 125, 1500), (flight.truth.t_ns, 100, 1200), (flight.gps.t_ns, 10, 120)):
        assert t_ns.dtype == np.int64 and t_ns[0] == EPOCH and len(t_ns) == count
        assert np.all(np.diff(t_ns) == 1_000_000_000 // rate)
    assert flight.imu.gyro.shape == flight.imu.accel.shape == (1500, 3)
    assert flight.truth.q.shape == (1200, 4) and flight.gps.p_ned.shape == (120, 3)


@pytest.mark.parametrize("scenario", ["book", "landfill"])
def test_static_start_reads_bias_and_gravity(scenario):
    flight = simulate_flight(scenario, 10.0, 5)
    still_truth = _seconds(flight.truth.t_ns) <= 5.0
    assert np.all(flight.truth.v[still_truth] == 0.0)
    assert np.all(flight.truth.p[still_truth] == flight.truth.p[0])
    assert np.all(flight.truth.q[still_truth] == flight.truth.q[0])
    still = _seconds(flight.imu.t_ns) <= 5.0
    g_b = quat_to_rot(flight.truth.q[0]).T @ np.array([0.0, 0.0, 9.80665])
    b_g, b_a = flight.truth.bias_g[still_truth].mean(axis=0), flight.truth.bias_a[still_truth].mean(axis=0)
    # Means of 626 samples: white noise leaves ~1.3e-4 rad/s and ~1e-3 m/s² of scatter.
    np.testing.assert_allclose(flight.imu.gyro[still].mean(axis=0), b_g, atol=6e-4)
    np.testing.assert_allclose(flight.imu.accel[still].mean(axis=0), -g_b + b_a, atol=5e-3)
    assert np.linalg.norm(b_g) > 1e-4  # a turn-on bias is really there


def test_book_stays_in_the_arm_envelope():
    flight = simulate_flight("book", 300.0, 0)
    kin = flight.trajectory.kinematics(_seconds(flight.truth.t_ns))
    moving = _seconds(flight.truth.t_ns) > 14.0
    height = -flight.truth.p[:, 2]
    assert 0.5 <= height.min() and height.max() <= 1.0
    horizontal = np.linalg.norm(flight.truth.p[:, :2] - flight.truth.p[0, :2], axis=1)
    assert 0.1 < horizontal.max() < 0.5
    speed = np.linalg.norm(flight.truth.v, axis=1)
    # A brisk arm (ABB IRB1400 class): enough acceleration for GPS to see the heading.
    assert speed.max() < 1.0 and 0.3 <= np.median(speed[moving]) <= 0.6
    roll, pitch, _ = np.degrees(euler_from_quat(flight.truth.q)).T
    assert 5.0 < max(np.abs(roll).max(), np.abs(pitch).max()) < 15.0
    yaw_swing = np.degrees(np.angle(np.exp(1j * (yaw_of(flight.truth.q) - yaw_of(flight.truth.q[0])))))
    assert 20.0 < np.abs(yaw_swing).max() < 35.0
    camera_down = kin.rotation()[:, 2, 2]  # world-down component of the body down axis
    assert camera_down.min() > np.cos(np.radians(20.0))


def test_landfill_flies_a_survey_at_altitude():
    scenario = LandfillScenario()
    trajectory = scenario.trajectory(1200.0, 9.80665)  # long enough to fly the lanes back again
    t = np.arange(0.0, 1200.0, 0.1)
    kin = trajectory.kinematics(t)
    label = trajectory.path.labels(t)
    surveying = np.isin(label, ["leg", "turn"])
    above_ground = scenario.ground_height(kin.p[:, 0], kin.p[:, 1]) - kin.p[:, 2]
    assert 30.0 <= above_ground[surveying].min() and above_ground[surveying].max() <= 60.0
    assert np.all(np.abs(above_ground[label == "static"] - scenario.imu_height_on_ground) < 1e-12)
    speed = np.linalg.norm(kin.v, axis=1)
    assert 5.0 <= speed[label == "leg"].min() and speed[label == "leg"].max() <= 10.0
    track = np.arctan2(kin.v[surveying, 1], kin.v[surveying, 0])
    nose_off_track = np.angle(np.exp(1j * (kin.euler[surveying, 2] - track)))
    assert np.abs(nose_off_track).max() < 1e-9
    # Thrust along body down: the specific force has no forward or sideways component.
    assert np.abs(kin.specific_force_b(9.80665)[:, :2]).max() < 1e-9
    assert np.count_nonzero(np.diff((label == "turn").astype(int)) == 1) >= 10


def test_gps_noise_has_the_thesis_covariance_and_lever_arm():
    flight = simulate_flight("landfill", 600.0, 11)
    kin = flight.trajectory.kinematics(_seconds(flight.gps.t_ns))
    antenna = kin.p + kin.rotation() @ np.array([0.0, 0.0, -0.3])
    error = flight.gps.p_ned - antenna
    std = error.std(axis=0)
    np.testing.assert_allclose(std, [1.0, 1.0, np.sqrt(2.0)], rtol=0.06)
    assert np.all(np.abs(error.mean(axis=0)) < 4.0 * std / np.sqrt(len(error)))
    assert np.all(flight.gps.sigma_h == 1.0) and np.allclose(flight.gps.sigma_v, np.sqrt(2.0))
    lag1 = np.corrcoef(error[:-1, 0], error[1:, 0])[0, 1]
    assert abs(lag1) < 0.1
    book = simulate_flight("book", 300.0, 11)
    book_error = book.gps.p_ned - book.trajectory.kinematics(_seconds(book.gps.t_ns)).p
    np.testing.assert_allclose(book_error.std(axis=0), [0.02, 0.02, 0.02 * np.sqrt(2.0)], rtol=0.08)


def test_gauss_markov_gps_error_is_correlated_with_the_same_sigma():
    model = GpsErrorModel(sigma_h=1.0, correlation_time_s=2.0)
    t = np.arange(40_000) * 0.1
    error = gps_errors(t, model, np.random.default_rng(1))
    np.testing.assert_allclose(error.std(axis=0), [1.0, 1.0, np.sqrt(2.0)], rtol=0.1)
    lag1 = np.corrcoef(error[:-1, 0], error[1:, 0])[0, 1]
    assert abs(lag1 - np.exp(-0.1 / 2.0)) < 0.01


def test_imu_noise_and_bias_random_walk_statistics():
    model = ImuErrorModel()
    n = 200_000
    errors = corrupt_imu(np.zeros((n, 3)), np.zeros((n, 3)), model, np.random.default_rng(2))
    dt = 1.0 / model.rate_hz
    steps_g, steps_a = np.diff(errors.bias_gyro, axis=0), np.diff(errors.bias_accel, axis=0)
    np.testing.assert_allclose(steps_g.std(axis=0), model.gyro_random_walk * np.sqrt(dt), rtol=0.02)
    np.testing.assert_allclose(steps_a.std(axis=0), model.accel_random_walk * np.sqrt(dt), rtol=0.02)
    white_g, white_a = errors.gyro - errors.bias_gyro, errors.accel - errors.bias_accel
    np.testing.assert_allclose(white_g.std(axis=0), model.gyro_noise_density * np.sqrt(model.rate_hz), rtol=0.02)
    np.testing.assert_allclose(white_a.std(axis=0), model.accel_noise_density * np.sqrt(model.rate_hz), rtol=0.02)
    one = np.zeros((1, 3))
    turn_on = np.array([corrupt_imu(one, one, model, np.random.default_rng(s)).bias_gyro[0] for s in range(600)])
    np.testing.assert_allclose(turn_on.std(), np.deg2rad(0.2), rtol=0.1)


def test_calibration_describes_the_simulated_sensors():
    landfill = simulate_flight("landfill", 8.0, 0).calibration
    assert landfill.gps.origin_lla == (58.43, 15.68, 60.0)
    np.testing.assert_array_equal(landfill.gps.lever_arm_b, [0.0, 0.0, -0.3])
    np.testing.assert_array_equal(landfill.imu.R_BI, np.eye(3))
    np.testing.assert_allclose(landfill.imu.noise.gyro_noise_density, 3e-4)
    np.testing.assert_array_equal(landfill.truth_point_b, np.zeros(3))
    book = simulate_flight("book", 8.0, 0)
    assert book.calibration.gps.origin_lla is None
    np.testing.assert_array_equal(book.calibration.gps.lever_arm_b, np.zeros(3))
    # The stated heading is the truth plus an error of the stated accuracy (as a crew would give it).
    sigma = book.calibration.initial_heading_sigma_rad
    assert sigma == pytest.approx(np.radians(0.3))
    error = book.calibration.initial_heading_rad - float(yaw_of(book.truth.q[0]))
    assert 0.0 < abs(error) < 4.0 * sigma
    other = simulate_flight("book", 8.0, 1).calibration.initial_heading_rad
    assert other != book.calibration.initial_heading_rad
    assert abs(book.calibration.initial_heading_rad) > 0.1


@pytest.mark.parametrize("scenario", ["book", "landfill"])
def test_a_flight_can_start_in_the_air(scenario):
    """``start_s``: the same trajectory joined mid-flight, moving from the first sample, no stated heading."""
    start = {"book": BookScenario().in_flight_s, "landfill": LandfillScenario().in_flight_s}[scenario]
    from_rest = simulate_flight(scenario, start + 5.0, 4)
    joined = simulate_flight(scenario, 5.0, 4, SimulationOptions(start_s=start))
    assert joined.truth.t_ns[0] == from_rest.truth.t_ns[0] == EPOCH  # the recording's clock starts at the epoch
    k = int(round(start * 100))
    np.testing.assert_allclose(joined.truth.p, from_rest.truth.p[k : k + len(joined.truth.p)], atol=1e-9)
    np.testing.assert_allclose(joined.truth.q, from_rest.truth.q[k : k + len(joined.truth.q)], atol=1e-9)
    assert np.linalg.norm(joined.truth.v[0]) > 0.1  # moving at the first sample
    assert joined.calibration.initial_heading_rad is None and joined.calibration.initial_heading_sigma_rad is None
    assert "starting in flight" in joined.description
    # Noise-free, its IMU is the exact derivative of the joined truth (nothing of the rest leaks in).
    exact = simulate_flight(scenario, 5.0, 4, SimulationOptions(imu=ImuErrorModel.perfect(), start_s=start))
    kin = exact.trajectory.kinematics(_seconds(exact.imu.t_ns))
    np.testing.assert_allclose(exact.imu.accel, kin.specific_force_b(9.80665), atol=1e-9)
    with pytest.raises(ValueError, match="start_s"):
        SimulationOptions(start_s=-1.0)


def test_ground_height_of_the_scenes():
    book = BookScenario()
    np.testing.assert_allclose(book.ground_height(np.array([0.0, 0.6, 3.0]), np.zeros(3)), [-0.035, 0.0, 0.75])
    landfill = LandfillScenario()
    assert landfill.ground_height(0.0, 0.0) == pytest.approx(0.0, abs=1e-12)
    hills = landfill.ground_height(np.array([250.0]), np.array([120.0]))
    assert hills[0] < -5.0  # a mound rises above the pad


def test_bad_arguments_are_refused_with_a_clear_message():
    with pytest.raises(ValueError, match="unknown scenario 'moon'"):
        simulate_flight("moon", 10.0, 0)
    with pytest.raises(ValueError, match="duration_s"):
        simulate_flight("book", 0.0, 0)
    with pytest.raises(ValueError, match="seed"):
        simulate_flight("book", 1.0, -1)
    with pytest.raises(ValueError, match="gyro_noise_density"):
        ImuErrorModel(gyro_noise_density=-1.0)


def test_a_five_minute_landfill_flight_has_every_sample():
    flight = simulate_flight("landfill", 300.0, 0)
    assert len(flight.imu.t_ns) == 300 * 125 and len(flight.gps.t_ns) == 300 * 10
