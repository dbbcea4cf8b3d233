"""IMU calibration: static stretches, gravity, gyro bias, roll/pitch and Allan figures with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.files.euroc_import import import_euroc
from vtolpose.drivers.simulator import BookScenario, ImuErrorModel, SimulationOptions, simulate_flight
from vtolpose.drivers.simulator.imu_model import corrupt_imu
from vtolpose.estimator.calibration.allan import allan_deviation, fit_noise
from vtolpose.estimator.calibration.imu import calibrate_imu
from vtolpose.estimator.calibration.static_detection import NoStaticStretchError, StaticOptions, find_static_stretches

RATE = 125.0
LONG_RATE = 50.0  # the long Allan record: densities do not depend on the rate, and 50 Hz is quicker


def static_imu(hours: float, model: ImuErrorModel, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A level IMU at rest for ``hours``: gyro and accel (N, 3) with the model's errors."""
    n = int(hours * 3600 * model.rate_hz)
    exact_f = np.tile([0.0, 0.0, -9.80665], (n, 1))
    errors = corrupt_imu(np.zeros((n, 3)), exact_f, model, np.random.default_rng(seed))
    return errors.gyro, errors.accel


@pytest.fixture(scope="module")
def two_hours_static():
    model = ImuErrorModel(rate_hz=LONG_RATE, gyro_noise_density=3e-4, gyro_random_walk=1e-4,
                          accel_noise_density=2e-3, accel_random_walk=1e-3)
    gyro, accel = static_imu(2.0, model, seed=7)
    return model, allan_deviation(np.hstack([gyro, accel]), LONG_RATE)


def test_allan_recovers_white_noise_within_10_percent(two_hours_static) -> None:
    model, curve = two_hours_static
    for k in range(6):
        truth = model.gyro_noise_density if k < 3 else model.accel_noise_density
        assert fit_noise(curve, k).white_noise == pytest.approx(truth, rel=0.10)


def test_allan_recovers_bias_random_walk(two_hours_static) -> None:
    # Two hours hold ~1400 crossover times; an Allan estimate of K then scatters by ~5 % per axis
    # (seeds 0-4: all 30 values within 8 %).
    model, curve = two_hours_static
    for sensor, channels, truth in (("gyro", range(3), model.gyro_random_walk), ("accel", range(3, 6), model.accel_random_walk)):
        values = np.array([fit_noise(curve, k).random_walk for k in channels], dtype=float)
        assert np.all(np.abs(values / truth - 1.0) < 0.15), (sensor, values / truth)
        assert np.mean(values) == pytest.approx(truth, rel=0.10), sensor


def test_bias_instability_is_the_curve_minimum_over_0_664(two_hours_static) -> None:
    model, curve = two_hours_static
    n, k = model.gyro_noise_density, model.gyro_random_walk
    sigma_min = math.sqrt(2.0 * n * k / math.sqrt(3.0))  # minimum of sqrt(N²/τ + K²τ/3)
    fit = fit_noise(curve, 0)
    assert fit.bias_instability == pytest.approx(sigma_min / 0.664, rel=0.10)
    assert not fit.bias_instability_is_bound


def test_a_short_record_does_not_pretend_to_know_the_random_walk() -> None:
    gyro, accel = static_imu(60.0 / 3600.0, ImuErrorModel(rate_hz=RATE), seed=1)
    curve = allan_deviation(np.hstack([gyro, accel]), RATE)
    fit = fit_noise(curve, 0)
    assert fit.random_walk is None
    assert fit.bias_instability_is_bound
    assert fit.white_noise == pytest.approx(3e-4, rel=0.10)


@pytest.fixture(scope="module")
def book(simulated_flight):
    model = ImuErrorModel(gyro_turn_on_bias_std=0.01, accel_turn_on_bias_std=0.01)
    return simulated_flight("book", 30.0, 4, SimulationOptions(imu=model))


def test_simulated_static_start_gives_bias_gravity_and_attitude(book) -> None:
    imu, truth = book.imu, book.truth
    result = calibrate_imu(imu.t_ns, imu.gyro, imu.accel, StaticOptions(min_duration_s=5.0))
    start, end = ((np.array([result.stretch.t0_ns, result.stretch.t1_ns]) - imu.t_ns[0]) * 1e-9)
    assert 0.0 <= start <= 1.5 and 8.0 <= end <= 10.0  # the book scenario rests for its first 10 s
    true_bias = truth.bias_g[truth.t_ns <= result.stretch.t1_ns].mean(axis=0)
    assert np.linalg.norm(result.gyro_bias - true_bias) < 0.1 * np.linalg.norm(true_bias)
    assert np.all(np.abs(result.gyro_bias - true_bias) < 4.0 * result.gyro_bias_sigma + 1e-5)
    assert result.gravity == pytest.approx(9.80665, abs=0.03)  # |g - b_a| with |b_a| ~ 0.017
    roll, pitch, _ = BookScenario().centre_euler  # the attitude it rests in
    tilt = 0.03 / 9.8  # accel bias of 0.03 m/s² tilts the estimate by at most this
    assert result.roll_rad == pytest.approx(roll, abs=tilt)
    assert result.pitch_rad == pytest.approx(pitch, abs=tilt)
    assert result.figure("gyro", "white_noise") == pytest.approx(np.full(3, 3e-4), rel=0.2)


def test_no_static_stretch_says_what_to_record(book) -> None:
    imu = book.imu
    moving = imu.t_ns >= imu.t_ns[0] + int(12e9)
    with pytest.raises(NoStaticStretchError, match=r"no static stretch of at least 10 s.*Record the vehicle standing still"):
        calibrate_imu(imu.t_ns[moving], imu.gyro[moving], imu.accel[moving])


def test_steady_straight_flight_is_not_rest_when_positions_say_so() -> None:
    flight = simulate_flight("landfill", 150.0, seed=3)
    imu, gps = flight.imu, flight.gps
    quiet = find_static_stretches(imu.t_ns, imu.gyro, imu.accel)
    assert quiet, "the IMU alone takes straight lanes at 8 m/s for rest"
    with pytest.raises(NoStaticStretchError, match=r"position fixes show the vehicle moving .* steady flight"):
        calibrate_imu(imu.t_ns, imu.gyro, imu.accel, positions=(gps.t_ns, gps.p_ned))


def test_euroc_mh01_rest_stretch_bias_and_gravity(euroc_mh01, tmp_path) -> None:
    import_euroc(euroc_mh01, tmp_path / "mh01", gps_rate_hz=10.0, gps_sigma_m=0.02)
    dataset = Dataset.open(tmp_path / "mh01")
    imu, gps = dataset.imu(), dataset.gps()
    result = calibrate_imu(imu.t_ns, imu.gyro, imu.accel, positions=(gps.t_ns, gps.p_ned))
    start, end = (np.array([result.stretch.t0_ns, result.stretch.t1_ns]) - imu.t_ns[0]) * 1e-9
    assert 21.0 <= start <= 23.5 and 39.0 <= end <= 44.5  # README: at rest from ~22 s, take-off near 45 s
    # Measured: 22.0-43.0 s, |f| = 9.7735 m/s², b_g = [0.0797, 0.0208, 0.0032] rad/s (body FRD).
    assert result.gravity == pytest.approx(9.7735, abs=0.005)
    np.testing.assert_allclose(result.gyro_bias, [0.0797, 0.0208, 0.0032], atol=0.002)
    assert any("vibration" in note for note in result.notes)
