"""The EuRoC causes bench's breakdowns: error by time since the last fix and the ratio per stretch, on made-up
errors whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from vtolpose.service.bench.euroc_causes import (
    GAP_EDGES_S, bench_euroc_causes, over_draws, rmse_by_gap, steady_state_ratio, stretch_ratios,
)


def test_the_error_is_filed_by_the_time_since_the_newest_fix():
    t = np.arange(int(1e9), int(21e9), int(0.005e9), dtype=np.int64)  # 200 Hz for 20 s
    fixes = np.arange(int(1e9), int(21e9), int(0.1e9), dtype=np.int64)  # 10 Hz
    since = (t - fixes[np.searchsorted(fixes, t, side="right") - 1]) * 1e-9
    error = np.zeros((len(t), 3))
    error[:, 2] = 0.01 + 0.2 * since  # grows by 2 cm per 100 ms of prediction
    bands = rmse_by_gap(t, error, fixes)
    assert len(bands) == len(GAP_EDGES_S) + 1
    assert bands[0] < bands[1] < bands[2] < bands[3] < bands[4]
    first = 0.01 + 0.2 * 0.005 * np.arange(4)  # 0, 5, 10 and 15 ms after a fix
    assert bands[0] == pytest.approx(np.sqrt(np.mean(first**2)), rel=1e-6)
    last = 0.01 + 0.2 * 0.005 * np.arange(16, 20)  # 80 to 95 ms
    assert bands[-1] == pytest.approx(np.sqrt(np.mean(last**2)), rel=1e-6)


def test_samples_before_the_first_fix_are_left_out():
    t = np.arange(0, int(10e9), int(0.005e9), dtype=np.int64)
    fixes = np.arange(int(5e9), int(10e9), int(0.1e9), dtype=np.int64)
    error = np.where((t < int(5e9))[:, None], 1.0, 0.01) * np.array([1.0, 0.0, 0.0])
    assert all(b == pytest.approx(0.01) for b in rmse_by_gap(t, error, fixes) if b is not None)


def test_each_stretch_is_scored_against_the_gps_in_the_same_stretch():
    t = np.arange(0.0, 120.0, 0.005)
    gps_t = np.arange(0.0, 120.0, 0.1)
    error = np.zeros((len(t), 3))
    gps_error = np.zeros((len(gps_t), 3))
    gps_error[:, 0] = np.where(gps_t < 60.0, 0.04, 0.02)
    error[:, 0] = np.where(t < 30.0, 0.03, 0.01)
    ratios = stretch_ratios(t, error, gps_t, gps_error, (15.0, 30.0, 60.0, 90.0))
    assert ratios == pytest.approx([0.75, 0.25, 0.5, 0.5])


def test_a_stretch_not_flown_has_no_figure():
    t = np.arange(0.0, 50.0, 0.005)
    gps_t = np.arange(0.0, 50.0, 0.1)
    ratios = stretch_ratios(t, np.full((len(t), 3), 0.01), gps_t, np.full((len(gps_t), 3), 0.02), (15.0, 30.0, 60.0))
    assert ratios[0] == pytest.approx(0.5) and ratios[1] == pytest.approx(0.5) and ratios[2] is None


def test_the_linear_filters_floor_matches_a_simulated_filter():
    """A Kalman filter run on a simulated double integrator (white acceleration, integrated finely) with noisy
    10-Hz fixes reaches the computed steady state, at the fixes and between them."""
    rng = np.random.default_rng(7)
    density, sigma, period, sub = 0.05, 0.02, 0.1, 20
    dt = period / sub
    F = np.array([[1.0, period], [0.0, 1.0]])
    Q = density**2 * np.array([[period**3 / 3, period**2 / 2], [period**2 / 2, period]])
    x_true, x, P = np.zeros(2), np.zeros(2), np.eye(2)
    at_fix, between = [], []
    for k in range(12000):
        for _ in range(sub):  # the truth: white acceleration held over fine steps; the filter predicts
            if k > 200:
                between.append(x[0] - x_true[0])
            a = rng.standard_normal() * density / np.sqrt(dt)
            x_true = x_true + np.array([x_true[1] * dt + 0.5 * a * dt**2, a * dt])
            x = np.array([x[0] + x[1] * dt, x[1]])
        P = F @ P @ F.T + Q
        K = P[:, 0] / (P[0, 0] + sigma**2)
        x = x + K * (x_true[0] + rng.standard_normal() * sigma - x[0])
        P = P - np.outer(K, P[0])
        if k > 200:
            at_fix.append(x[0] - x_true[0])
    at, over = steady_state_ratio(density, 1.0 / period, sigma, sigma)
    assert np.sqrt(np.mean(np.square(at_fix))) / sigma == pytest.approx(at, rel=0.04)
    assert np.sqrt(np.mean(np.square(between))) / sigma == pytest.approx(over, rel=0.04)
    assert at < over < 1.0


def test_the_floor_falls_with_the_noise_density():
    figures = [steady_state_ratio(d, 10.0, 0.02, 0.02 * np.sqrt(2)) for d in (0.05, 0.03, 0.02)]
    assert figures[0][0] > figures[1][0] > figures[2][0] and figures[0][1] > figures[1][1] > figures[2][1]


def test_the_axes_combine_by_their_gps_variances():
    """x, y at σ_h and z at σ_v: the combined figure is the axes' error variances over the GPS's, summed."""
    h, v = 0.02, 0.02 * np.sqrt(2)
    both = np.array(steady_state_ratio(0.05, 10.0, h, v))
    flat_h = np.array(steady_state_ratio(0.05, 10.0, h, h))  # every axis at σ_h: one axis' ratio
    flat_v = np.array(steady_state_ratio(0.05, 10.0, v, v))
    expected = np.sqrt((2 * (flat_h * h) ** 2 + (flat_v * v) ** 2) / (2 * h**2 + v**2))
    assert both == pytest.approx(expected, rel=1e-9)
    assert not np.allclose(flat_h, flat_v, rtol=1e-3)  # the vertical's larger noise changes its ratio


def test_without_flights_the_bench_says_where_to_put_them(tmp_path, monkeypatch):
    monkeypatch.setenv("VTOLPOSE_EUROC_DATA", str(tmp_path))
    lines: list[str] = []
    assert bench_euroc_causes(lines.append) == []
    assert len(lines) == 1 and "skipped" in lines[0] and "VTOLPOSE_EUROC_DATA" in lines[0]


def test_draws_of_the_gps_noise_are_summed_up_per_flight_and_per_stretch():
    """The ratio's mean and range over draws; a stretch's mean over the draws that reach it, none: no figure."""
    draws = [(0.60, (0.68, 0.65, 0.58)), (0.58, (0.58, 0.60, None)), (0.56, (0.53, 0.61, 0.56))]
    mean, least, most, stretches = over_draws(draws)
    assert mean == pytest.approx(0.58) and least == 0.56 and most == 0.60
    assert stretches == pytest.approx(((0.68 + 0.58 + 0.53) / 3, (0.65 + 0.60 + 0.61) / 3, (0.58 + 0.56) / 2))
    assert over_draws([(0.5, (0.5, None))])[3] == (0.5, None)
