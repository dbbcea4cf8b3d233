"""The per-run sample checks (``screen_rows``, ``plain_run``): whole-column arithmetic that must give, compiled
and interpreted alike, what the per-sample checks they replace give, row by row."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vtolpose.estimator.inertial import sample_kernel


def _row_by_row(gyro: np.ndarray, accel: np.ndarray, gyro2_max: float, accel2_max: float):
    exceeded, finite = [], []
    for (gx, gy, gz), (ax, ay, az) in zip(gyro.tolist(), accel.tolist()):
        g2, a2 = gx * gx + gy * gy + gz * gz, ax * ax + ay * ay + az * az
        finite.append(math.isfinite(gx * gx + gy * gy + gz * gz + ax * ax + ay * ay + az * az))
        exceeded.append((g2 > gyro2_max or a2 > accel2_max) and math.isfinite(g2 + a2))
    return np.array(exceeded, bool), np.array(finite, bool)


def _rows(seed: int, n: int = 64) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    gyro, accel = rng.normal(scale=20.0, size=(n, 3)), rng.normal(scale=150.0, size=(n, 3))
    gyro[3, 1], accel[5, 2], gyro[7, 0], accel[9, 0] = np.nan, np.inf, 1e200, -1e160  # overflow in the sums
    accel[11] = [1e154, 1e154, 1e154]  # each square finite, their sum not
    return gyro, accel


@pytest.mark.filterwarnings("ignore:overflow:RuntimeWarning")  # interpreted, numpy says so; the row-by-row floats do not
@pytest.mark.parametrize("kernel", ["compiled", "interpreted"])
@pytest.mark.parametrize("limits", [(math.inf, math.inf), (2700.0, 76800.0)])
def test_screen_rows_is_the_per_row_check(kernel, limits):
    screen = sample_kernel.screen_rows if kernel == "compiled" else sample_kernel.screen_rows.py_func
    for seed in range(4):
        gyro, accel = _rows(seed)
        exceeded, finite = screen(gyro, accel, *limits)
        want_exceeded, want_finite = _row_by_row(gyro, accel, *limits)
        assert np.array_equal(exceeded, want_exceeded) and np.array_equal(finite, want_finite)
        assert not finite[[3, 5, 7, 9, 11]].any() and finite[[0, 1, 2]].all()
        if limits[0] < math.inf:
            assert exceeded.any() and not exceeded.all()


@pytest.mark.parametrize("kernel", ["compiled", "interpreted"])
def test_plain_run_takes_only_runs_in_order_without_gaps_and_finite(kernel):
    plain = sample_kernel.plain_run if kernel == "compiled" else sample_kernel.plain_run.py_func
    t = 1_000_000_000 + np.arange(10, dtype=np.int64) * 5_000_000
    rng = np.random.default_rng(1)
    gyro, accel = rng.normal(size=(10, 3)), rng.normal(size=(10, 3))
    assert plain(t, gyro, accel, int(t[0]) - 5_000_000, 0.1)
    assert plain(t[:0], gyro[:0], accel[:0], 0, 0.1)  # nothing to refuse
    assert not plain(t, gyro, accel, int(t[0]), 0.1)  # the first sample no later than the last taken
    assert not plain(t, gyro, accel, int(t[0]) - 200_000_000, 0.1)  # a gap before the first
    late = t.copy()
    late[6:] += 200_000_000
    assert not plain(late, gyro, accel, int(t[0]) - 5_000_000, 0.1)  # a gap inside the run
    back = t.copy()
    back[4] = back[3]
    assert not plain(back, gyro, accel, int(t[0]) - 5_000_000, 0.1)  # a repeated time
    for rows in (gyro, accel):
        bad = rows.copy()
        bad[8, 1] = np.nan
        assert not plain(t, bad if rows is gyro else gyro, bad if rows is accel else accel, int(t[0]) - 5_000_000, 0.1)
