"""The NEES of a run scored from its start (no absolute position): the origin's variance at the start is a gauge
the shift onto the truth takes off the errors, so it comes off the covariance too (service/replay/report.py)."""

from __future__ import annotations

import numpy as np

from vtolpose.service.replay.report import StartAlignment, relative_samples
from vtolpose.service.replay.session import CovarianceSamples


def samples(position_var: list[float]) -> CovarianceSamples:
    """Four pose covariances: the given position variance on each axis, 0.01 rad² on each attitude axis."""
    n = len(position_var)
    cov = np.zeros((n, 6, 6))
    for k, var in enumerate(position_var):
        cov[k] = np.diag([var] * 3 + [1e-2] * 3)
        cov[k, 0, 3] = cov[k, 3, 0] = 1e-7  # a position–attitude correlation the gauge has no part in
    return CovarianceSamples(np.arange(n, dtype=np.int64) * 10, np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)), cov)


def test_the_start_origin_variance_comes_off_and_the_start_pose_is_not_scored():
    origin = 4e-6  # (2 mm)², what a visual-inertial start gives its frame's origin
    cov = samples([origin, origin + 1e-6, origin + 4e-6, origin + 9e-6])
    align = StartAlignment(np.eye(3), np.zeros(3), np.zeros(3), True, np.eye(3) * origin, pivot_t_ns=10)
    rel = relative_samples(cov, align)
    assert rel.t_ns.tolist() == [20, 30]  # the start's and the pivot's own errors are zero by construction
    np.testing.assert_allclose(np.diagonal(rel.cov, axis1=1, axis2=2)[:, 0:3], [[4e-6] * 3, [9e-6] * 3])
    np.testing.assert_array_equal(rel.cov[:, 3:6, :], cov.cov[2:, 3:6, :])  # attitude and its correlations kept


def test_a_start_again_with_a_smaller_origin_keeps_the_filters_covariance():
    cov = samples([4e-6, 5e-6, 1e-6])  # the camera lost, a new start with an origin of its own (1 mm)
    align = StartAlignment(np.eye(3), np.zeros(3), np.zeros(3), True, np.eye(3) * 4e-6)
    rel = relative_samples(cov, align)
    np.testing.assert_allclose(rel.cov[0, 0:3, 0:3], np.eye(3) * 1e-6)
    np.testing.assert_array_equal(rel.cov[1], cov.cov[2])


def test_without_a_gauge_nothing_changes():
    cov = samples([4e-6, 5e-6])
    align = StartAlignment(np.eye(3), np.zeros(3), np.zeros(3), False)
    np.testing.assert_array_equal(align.relative(cov.cov), cov.cov)
