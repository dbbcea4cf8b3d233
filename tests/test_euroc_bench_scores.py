"""The EuRoC bench's error breakdown: RMSE per speed band and the worst 10-s stretch, on made-up tracks."""

from __future__ import annotations

import numpy as np
import pytest

from vtolpose.service.bench.euroc import SPEED_BANDS_M_S, speed_band_rmse, worst_window


def _track(speeds_m_s: list[float], seconds_each: float = 5.0, rate_hz: float = 100.0):
    """A straight track at each speed in turn; t in ns."""
    t, p, x = [], [], 0.0
    for k, v in enumerate(speeds_m_s):
        for i in range(int(seconds_each * rate_hz)):
            t.append(int((k * seconds_each + i / rate_hz) * 1e9))
            p.append([x, 0.0, 0.0])
            x += v / rate_hz
    return np.array(t, dtype=np.int64), np.array(p)


def test_each_band_gets_the_error_flown_at_its_speed():
    t, p = _track([0.2, 0.8, 1.2, 2.5])
    error = np.zeros((len(t), 3))
    quarter = len(t) // 4
    for k, e in enumerate([0.01, 0.02, 0.03, 0.05]):
        error[k * quarter : (k + 1) * quarter, 1] = e
    bands = speed_band_rmse(t, p, error)
    assert len(bands) == len(SPEED_BANDS_M_S) + 1
    # The gradient blurs one sample at each change of speed.
    assert bands == pytest.approx([0.01, 0.02, 0.03, 0.05], rel=0.05)


def test_a_band_never_flown_has_no_figure():
    t, p = _track([0.2, 0.3])
    bands = speed_band_rmse(t, p, np.full((len(t), 3), 0.01))
    assert bands[0] == pytest.approx(np.sqrt(3) * 0.01) and bands[1:] == (None, None, None)


def test_the_worst_window_finds_the_bad_stretch():
    t = np.arange(0, int(60e9), int(0.01e9), dtype=np.int64)
    error = np.zeros((len(t), 3))
    bad = (t >= int(31e9)) & (t < int(41e9))
    error[bad, 0] = 0.1
    rmse, start_s = worst_window(t, error, int(t[0]) - int(2e9))
    assert rmse == pytest.approx(0.1, rel=1e-6) and start_s == pytest.approx(33.0)


def test_a_span_shorter_than_the_window_has_no_worst_window():
    t = np.arange(0, int(5e9), int(0.01e9), dtype=np.int64)
    assert worst_window(t, np.zeros((len(t), 3)), 0) is None
