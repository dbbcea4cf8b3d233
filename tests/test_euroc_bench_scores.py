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


def test_at_the_fixes_only_the_first_pose_at_or_after_each_fix_is_scored():
    """The smoother's own measure: an estimate that is exact at each fix's update and wrong in between scores 0 there,
    and its error at a fix counts in full (no alignment takes it away); nothing before SCORE_FROM_S counts."""
    from types import SimpleNamespace

    from vtolpose.service.bench.euroc import SCORE_FROM_S, at_fix_position_rmse

    t_truth = np.arange(0, 40_000_000_000, 5_000_000, dtype=np.int64)  # 200 Hz for 40 s
    p_truth = np.column_stack([np.sin(t_truth * 1e-9), np.cos(t_truth * 1e-9), 0.1 * t_truth * 1e-9])
    t_fix = np.arange(0, 40_000_000_000, 100_000_000, dtype=np.int64) + 2_500_000  # 10 Hz, between truth samples
    point_b = np.array([0.1, 0.0, 0.0])
    dataset = SimpleNamespace(truth=lambda: SimpleNamespace(t_ns=t_truth, p=p_truth),
                              gps=lambda: SimpleNamespace(t_ns=t_fix), calibration=SimpleNamespace(truth_point_b=point_b))
    t_est = np.sort(np.concatenate([t_truth, t_fix]))
    truth_at = np.column_stack([np.interp(t_est, t_truth, p_truth[:, c]) for c in range(3)])
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(t_est), 1))
    at_fix = np.isin(t_est, t_fix)
    p_est = truth_at - point_b + np.where(at_fix[:, None], 0.0, 0.3)  # 0.3 m off everywhere but at the fixes
    assert at_fix_position_rmse(SimpleNamespace(t_ns=t_est, p=p_est, q=q), dataset) == pytest.approx(0.0, abs=1e-12)
    late = t_est >= int(SCORE_FROM_S * 1e9)
    p_est[at_fix & late] += [0.0, 0.04, 0.0]  # a 4-cm error at every scored fix
    p_est[at_fix & ~late] += [5.0, 0.0, 0.0]  # and a large one before the scored stretch: not counted
    assert at_fix_position_rmse(SimpleNamespace(t_ns=t_est, p=p_est, q=q), dataset) == pytest.approx(0.04, rel=1e-9)
