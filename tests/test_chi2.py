"""χ² quantiles computed without scipy agree with scipy's, across gates, bands and tails."""

from __future__ import annotations

import math

import pytest
from scipy.special import chdtri

from vtolpose.estimator.core.chi2 import lower_tail, upper_quantile, upper_tail
from vtolpose.estimator.core.kalman import chi2_gate

TAILS = (1e-12, 1e-9, 1e-6, 1e-4, 1e-3, 0.0027, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 0.75, 0.9, 0.95, 0.975, 0.99,
         0.999, 1 - 1e-6)


@pytest.mark.parametrize("dof", [0.5, 1, 2, 2.5, 3, 6, 7.3, 15, 40, 100, 300, 1000, 30_000, 300_000])
def test_quantiles_agree_with_scipy(dof: float) -> None:
    tolerance = 1e-13 if dof <= 1000 else 1e-11  # the prefactor's cancellation grows with dof
    for tail in TAILS:
        assert upper_quantile(dof, tail) == pytest.approx(float(chdtri(dof, tail)), rel=tolerance), tail


def test_gates_for_every_update_size_agree_with_scipy_to_the_last_bits() -> None:
    for dof in range(1, 201):
        for probability in (0.9, 0.95, 0.99, 0.999, 0.9999):
            assert chi2_gate(dof, probability) == pytest.approx(float(chdtri(dof, 1 - probability)), rel=1e-14)


def test_tails_are_complementary_and_invert_the_quantile() -> None:
    for dof in (1, 3, 6, 50):
        for x in (0.01, 1.0, dof, 3.0 * dof + 10.0):
            assert upper_tail(dof, x) + lower_tail(dof, x) == pytest.approx(1.0, abs=1e-15)
        x = upper_quantile(dof, 1e-9)
        assert upper_tail(dof, x) == pytest.approx(1e-9, rel=1e-12)
    assert upper_tail(3, 0.0) == 1.0 and lower_tail(3, -1.0) == 0.0
    assert upper_tail(2, 4.0) == pytest.approx(math.exp(-2.0), rel=1e-15)  # χ²₂ is exponential: closed form


@pytest.mark.parametrize("dof, tail", [(0, 0.05), (-1, 0.05), (3, 0.0), (3, 1.0), (3, math.nan)])
def test_bad_arguments_say_which(dof: float, tail: float) -> None:
    with pytest.raises(ValueError, match="degrees of freedom" if dof <= 0 else "tail probability"):
        upper_quantile(dof, tail)

