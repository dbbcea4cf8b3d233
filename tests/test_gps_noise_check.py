"""The GPS noise check's order statistics: numpy's median and percentile, bit for bit, on sorted Python floats."""

import math

import numpy as np
import pytest

from vtolpose.estimator.core.measurements import GpsFix
from vtolpose.estimator.core.state import FilterState, StateLayout
from vtolpose.estimator.gnss.gps_update import GpsModel
from vtolpose.estimator.gnss.noise_check import (
    LOWER_DECILE_ABS, MAD_TO_SIGMA, GpsNoiseCheck, SortedSizes, median_of_sorted, percentile_of_sorted,
)


def samples() -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    out = [np.abs(rng.normal(size=n)) * 10.0 ** rng.uniform(-3, 2) for n in range(1, 210)]
    out += [np.round(rng.uniform(0, 3, size=n), 1) for n in (2, 5, 20, 200)]  # ties
    out += [np.array([0.0, 0.0, 1.0, math.inf]), np.array([math.inf]), np.array([1.0, math.nan, 2.0]), np.zeros(7)]
    return out


def rng_order(values: np.ndarray) -> list[float]:
    return np.random.default_rng(len(values)).permutation(values).tolist()


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")  # numpy's own inf − inf, NaN as ours
@pytest.mark.parametrize("q", [10, 25, 50, 90])
def test_the_order_statistics_are_numpys(q):
    for values in samples():
        sizes = SortedSizes()
        for size in rng_order(values):  # kept in order as they come, NaN counted apart
            sizes.add(size)
        np.testing.assert_array_equal(sizes.median(), np.median(values))
        np.testing.assert_array_equal(sizes.percentile(q / 100), np.percentile(values, q))
        finite = values[~np.isnan(values)]
        if len(finite) == len(values):
            in_order = sorted(values.tolist())
            np.testing.assert_array_equal(median_of_sorted(in_order), np.median(values))
            np.testing.assert_array_equal(percentile_of_sorted(in_order, q / 100), np.percentile(values, q))


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")  # numpy's percentile of a NaN
def test_the_measured_scatter_is_the_one_numpy_gives_for_the_window():
    """Fed fixes through the filter's hooks, the check's scatter (median and lower decile of the differences'
    sizes, kept in order as they come and go) is the numpy formula's on the same differences, also once the
    window is full and slides, and while a difference that is not finite is in it."""
    check = GpsNoiseCheck(sigma_floor_m=1e-3)
    state = FilterState(StateLayout("biases"))
    state.cov = np.eye(15) * 0.01
    model = GpsModel(np.zeros(3))
    rng = np.random.default_rng(3)
    diffs, last = [], None
    for k in range(130):
        fix = GpsFix(k * 100_000_000, rng.normal(size=3) * [0.5, 0.5, 1.0], 0.02, 0.03)
        check.before_update(state, fix, model)
        residual = rng.normal(size=3) * 0.01
        if k in (10, 11):  # a residual not finite: NaN in the window until it slides out
            residual[k - 10] = math.nan
        check.after_update(fix.t_ns, residual, True)
        if last is not None:
            diffs.append(fix.p_ned - last)
        last = residual
        window = np.array(diffs[-check.options.window:])
        if len(window) < check.options.min_pairs_after_resets:
            assert check.measured_sigmas() is None
            continue
        h = MAD_TO_SIGMA * float(np.median(np.abs(window[:, :2]))) / math.sqrt(2.0)
        v = MAD_TO_SIGMA * float(np.median(np.abs(window[:, 2]))) / math.sqrt(2.0)
        np.testing.assert_array_equal(check.measured_sigmas(), (min(max(h, 1e-3), 50.0), min(max(v, 1e-3), 50.0)))
        robust = float(np.percentile(np.abs(window[:, :2]), 10)) / (LOWER_DECILE_ABS * math.sqrt(2.0))
        np.testing.assert_array_equal(check.robust_sigma_h(), robust)
        nan_in_window = 11 <= k <= 12 + check.options.window - 1
        assert math.isnan(robust) == nan_in_window
        # The NIS window's lower quartile (the verdict's "out of band"), kept in order as the window slides.
        np.testing.assert_array_equal(check._nis_sizes.percentile(0.25), np.percentile(list(check._nis), 25))
