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
