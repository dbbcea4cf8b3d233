"""The IMU's vibration floor: a known white density comes back, slow motion below the band does not leak in."""

from __future__ import annotations

import numpy as np
import pytest

from vtolpose.estimator.inertial.vibration import spectral_density, vibration_floor

RATE_HZ = 200.0


def test_a_white_noise_comes_back_at_its_density_per_axis():
    rng = np.random.default_rng(3)
    density = np.array([0.02, 0.05, 0.1])  # m/s²/√Hz
    samples = rng.standard_normal((200 * 120, 3)) * density * np.sqrt(RATE_HZ / 2.0)  # white at that density
    assert vibration_floor(samples, RATE_HZ) == pytest.approx(density, rel=0.03)


def test_the_vehicles_motion_below_the_band_is_left_out():
    rng = np.random.default_rng(4)
    t = np.arange(200 * 120) / RATE_HZ
    motion = 2.0 * np.sin(2 * np.pi * 0.3 * t) + 1.0 * np.sin(2 * np.pi * 2.1 * t)  # m/s², far above the noise
    samples = (motion + rng.standard_normal(len(t)) * 0.05 * np.sqrt(RATE_HZ / 2.0))[:, None]
    assert vibration_floor(samples, RATE_HZ)[0] == pytest.approx(0.05, rel=0.03)
    assert vibration_floor(samples, RATE_HZ, band_hz=(0.2, 3.0))[0] > 0.5  # where the motion is, it dominates


def test_a_rotor_line_inside_the_band_counts():
    t = np.arange(200 * 60) / RATE_HZ
    amplitude = 0.5
    samples = (amplitude * np.sin(2 * np.pi * 31.3 * t))[:, None]
    freq, density = spectral_density(samples, RATE_HZ)
    power = np.sum(density[:, 0]) * (freq[1] - freq[0])
    assert power == pytest.approx(amplitude**2 / 2.0, rel=0.02)  # Parseval: a sine's variance is A²/2


@pytest.mark.parametrize("samples, band, message", [
    (np.zeros((100, 3)), (10.0, 60.0), "fewer than one segment"),
    (np.zeros((4096, 3)), (10.0, 150.0), "Nyquist"),
    (np.zeros((4096, 3)), (60.0, 10.0), "Nyquist"),
])
def test_bad_input_says_what_was_wrong(samples, band, message):
    with pytest.raises(ValueError, match=message):
        vibration_floor(samples, RATE_HZ, band)


def _flight(seconds: float = 300.0, truth_hz: float = 100.0):
    """A vehicle swinging and turning: its track at ``truth_hz``, its true specific force at 200 Hz."""
    def track(t):
        p = np.stack([3.0 * np.sin(2 * np.pi * 0.11 * t), 2.0 * np.sin(2 * np.pi * 0.23 * t + 1.0),
                      -1.0 + 0.5 * np.sin(2 * np.pi * 0.7 * t)], axis=-1)
        a = np.stack([-3.0 * (2 * np.pi * 0.11) ** 2 * np.sin(2 * np.pi * 0.11 * t),
                      -2.0 * (2 * np.pi * 0.23) ** 2 * np.sin(2 * np.pi * 0.23 * t + 1.0),
                      -0.5 * (2 * np.pi * 0.7) ** 2 * np.sin(2 * np.pi * 0.7 * t)], axis=-1)
        yaw, roll = 0.8 * np.sin(2 * np.pi * 0.05 * t), 0.2 * np.sin(2 * np.pi * 0.4 * t)
        cy, sy, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(roll), np.sin(roll)
        one, zero = np.ones_like(t), np.zeros_like(t)
        Rz = np.stack([np.stack([cy, -sy, zero], -1), np.stack([sy, cy, zero], -1), np.stack([zero, zero, one], -1)], -2)
        Rx = np.stack([np.stack([one, zero, zero], -1), np.stack([zero, cr, -sr], -1), np.stack([zero, sr, cr], -1)], -2)
        cy2, sy2, cr2, sr2 = np.cos(yaw / 2), np.sin(yaw / 2), np.cos(roll / 2), np.sin(roll / 2)
        q = np.stack([cy2 * cr2, cy2 * sr2, sy2 * sr2, sy2 * cr2], axis=-1)  # q(yaw about z) ⊗ q(roll about x)
        return p, a, Rz @ Rx, q
    gravity = np.array([0.0, 0.0, 9.81])  # NED: down
    R_bi = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # EuRoC's IMU, x up
    truth_t = np.arange(0.0, seconds, 1.0 / truth_hz)
    p, _, _, q = track(truth_t)
    imu_t = np.arange(0.0, seconds, 1.0 / RATE_HZ)
    _, a, R_imu, _ = track(imu_t)
    f_i = np.einsum("nji,nj->ni", R_imu, a - gravity) @ R_bi
    as_ns = lambda t: np.round(t * 1e9).astype(np.int64)  # noqa: E731
    return as_ns(imu_t), f_i, as_ns(truth_t), p, q, R_bi, gravity


@pytest.mark.parametrize("truth_hz", [20.0, 200.0])
def test_the_accelerometers_error_below_a_few_hertz_comes_back_through_the_motion_and_a_rotor(truth_hz):
    """A white error of known density added to the true specific force, plus a strong 31-Hz rotor line: the
    residual against the truth's track shows the error's density in every low band, not the motion, not the rotor;
    a wrong mounting shows at once."""
    from vtolpose.estimator.inertial.vibration import band_densities, specific_force_residual

    imu_t, f_i, truth_t, p, q, R_bi, gravity = _flight(truth_hz=truth_hz)
    rng = np.random.default_rng(7)
    density = np.array([0.01, 0.03, 0.06])
    rotor = 2.0 * np.sin(2 * np.pi * 31.0 * imu_t * 1e-9)[:, None]
    accel = f_i + rotor + rng.standard_normal(f_i.shape) * density * np.sqrt(RATE_HZ / 2.0)
    residual, rate = specific_force_residual(imu_t, accel, truth_t, p, q, R_bi, gravity)
    assert rate == pytest.approx(truth_hz)
    found = band_densities(residual, rate)
    assert found.shape == (3, 3)
    assert found == pytest.approx(np.tile(density, (3, 1)), rel=0.2)
    wrong_mounting = specific_force_residual(imu_t, accel, truth_t, p, q, np.eye(3), gravity)[0]
    assert np.all(band_densities(wrong_mounting, rate)[:2].max(axis=1) > 10 * density.max())


def test_a_truth_too_coarse_for_the_fit_is_refused():
    from vtolpose.estimator.inertial.vibration import specific_force_residual

    imu_t, f_i, truth_t, p, q, R_bi, gravity = _flight(seconds=60.0, truth_hz=5.0)
    with pytest.raises(ValueError, match="too coarse"):
        specific_force_residual(imu_t, f_i, truth_t, p, q, R_bi, gravity)
