"""The EuRoC causes bench's breakdowns: error by time since the last fix and the ratio per stretch, on made-up
errors whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from vtolpose.service.bench.euroc_causes import GAP_EDGES_S, rmse_by_gap, stretch_ratios


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
