"""The GPS update's outlier gate as configured by default: an outlier test, not a tenth of the good fixes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vtolpose.config import load_config
from vtolpose.estimator.core.measurements import GpsFix
from vtolpose.estimator.core.rotation import quat_from_euler
from vtolpose.estimator.core.state import FilterState, StateLayout
from vtolpose.estimator.core.calibration import ImuNoise
from vtolpose.estimator.filter import FilterOptions
from vtolpose.estimator.gnss.gps_update import GpsUpdater
from vtolpose.service.runtime.wiring import filter_options

SIGMA = 0.5  # m, the fix's; the state's position variance adds to it


def fix_at_nis(nis: float) -> tuple[FilterState, GpsFix]:
    """A level state and a fix whose NIS against it is ``nis`` (the offset along north, in innovation sigmas)."""
    state = FilterState(StateLayout("biases"))
    state.q = quat_from_euler(0.0, 0.0, 0.7)
    state.cov = np.eye(15) * 1e-4
    s_north = 1e-4 + SIGMA**2
    return state, GpsFix(0, np.array([math.sqrt(nis * s_north), 0.0, 0.0]), SIGMA, SIGMA)


@pytest.mark.parametrize("where", ["config", "options"])
def test_a_fix_with_nis_ten_is_taken_and_one_beyond_the_999_quantile_is_not(where: str) -> None:
    """3 dof: the 95 % quantile (7.81) would throw away one good fix in twenty; the default is the 99.9 % one
    (16.27), in the configuration file and in the estimator's own options alike."""
    gate = (filter_options(load_config(None), ImuNoise.isotropic(2e-3, 2e-5, 5e-2, 3e-3)).gps_gate if where == "config"
            else FilterOptions().gps_gate)
    assert gate == pytest.approx(16.27)
    updater = GpsUpdater(np.zeros(3), gate)
    state, fix = fix_at_nis(10.0)
    taken = updater.update(state, fix)
    assert taken.accepted and taken.nis == pytest.approx(10.0)
    state, fix = fix_at_nis(17.0)
    refused = updater.update(state, fix)
    assert not refused.accepted and refused.reason == "chi2 gate" and refused.nis == pytest.approx(17.0)
