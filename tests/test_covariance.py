"""Covariance surgery (estimator/core/covariance.py): the operations by named block, and no literal
covariance slice anywhere else in the estimator."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from vtolpose.estimator.core import covariance
from vtolpose.estimator.core.state import LANDMARK_DIM, StateLayout

ESTIMATOR = Path(__file__).resolve().parent.parent / "estimator"
# cov[3:6, ...], cov9[:, 0:3], np.diagonal(cov)[9:12], P[6:9]: a covariance indexed by literal numbers.
LITERAL_SLICE = re.compile(r"\b(cov\w*|np\.diag(?:onal)?\(\s*[\w.]*cov\w*\s*\))\s*\[[^\]]*(?<![\w.])\d+\s*:")


def _spd(n: int, seed: int = 0) -> np.ndarray:
    a = np.random.default_rng(seed).normal(size=(n, n))
    return a @ a.T + n * np.eye(n)


def test_no_literal_covariance_slices_outside_the_surgery_module():
    offenders = []
    for path in sorted(ESTIMATOR.rglob("*.py")):
        if path.name == "covariance.py":
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if LITERAL_SLICE.search(line):
                offenders.append(f"{path.relative_to(ESTIMATOR.parent)}:{number}: {line.strip()}")
    assert not offenders, "covariance indexed by literal numbers (use core/covariance.py's named blocks):\n" + \
        "\n".join(offenders)


def test_the_grep_sees_what_it_must():
    for line in ("state.cov[3:6, :] = 0.0", "x = np.diagonal(state.cov)[9:12]", "cov9[:, 0:3] = 0",
                 "np.diag(start.cov)[15 + 5 :: 6]"):
        assert LITERAL_SLICE.search(line), line
    assert not LITERAL_SLICE.search("state.cov[V, V] = velocity_cov")


def test_reinitialise_decorrelates_the_block_and_sets_it():
    cov = _spd(15)
    block = np.diag([1.0, 2.0, 3.0])
    covariance.reinitialise(cov, covariance.V, block)
    assert np.array_equal(cov[covariance.V, covariance.V], block)
    others = np.r_[0:3, 6:15]
    assert not cov[3:6][:, others].any() and not cov[others][:, 3:6].any()
    assert np.allclose(cov, cov.T)


def test_forget_yaw_zeroes_its_row_and_column_only():
    cov = _spd(9)
    before = cov.copy()
    covariance.forget_yaw(cov)
    assert not cov[covariance.YAW].any() and not cov[:, covariance.YAW].any()
    keep = np.r_[0:8]
    assert np.array_equal(cov[np.ix_(keep, keep)], before[np.ix_(keep, keep)])


def test_robot_reset_keeps_position_variances_and_sizes_for_the_model():
    var_p = np.array([1.0, 2.0, 3.0])
    for variant, n in (("thesis", 9), ("biases", 15)):
        cov = covariance.robot_reset(StateLayout(variant), var_p, 0.5, 0.1, 0.01, 0.2)
        assert cov.shape == (n, n)
        assert np.array_equal(np.diag(cov)[:3], var_p)
        assert np.allclose(np.diag(cov)[3:9], [0.25] * 3 + [0.01] * 3)
        assert np.count_nonzero(cov - np.diag(np.diag(cov))) == 0


def test_append_then_keep_states_round_trips():
    cov = _spd(9)
    rng = np.random.default_rng(1)
    cross, new = rng.normal(size=(LANDMARK_DIM, 9)), _spd(LANDMARK_DIM, 2)
    grown = covariance.append_states(cov, cross, new)
    assert grown.shape == (15, 15) and np.allclose(grown, grown.T)
    assert np.array_equal(grown[9:, :9], cross)
    keep = np.r_[0:9]
    assert np.array_equal(covariance.keep_states(grown, keep), cov)


def test_landmark_sigmas_and_robot_and_map():
    n_robot, n_landmarks = 15, 3
    cov = np.diag(np.arange(1.0, n_robot + LANDMARK_DIM * n_landmarks + 1.0))
    rho = covariance.landmark_sigmas(cov, n_robot, 5)
    assert np.allclose(rho**2, [n_robot + 6, n_robot + 12, n_robot + 18])
    thesis = covariance.robot_and_map(cov, n_robot, 9)
    assert thesis.shape == (9 + 18, 9 + 18)
    assert np.array_equal(np.diag(thesis)[9:], np.diag(cov)[15:])
