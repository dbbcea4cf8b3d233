"""The start's sample window (``initializer.SampleWindow``): its arrays hold exactly the samples of the last
``span`` in order, whatever the growing and moving inside, as a queue of rows stacked would."""

from __future__ import annotations

from collections import deque

import numpy as np

from vtolpose.estimator.inertial.initializer import SampleWindow


def test_the_window_holds_the_samples_of_its_span_in_order() -> None:
    rng = np.random.default_rng(7)
    window, reference = SampleWindow(capacity=4), deque()
    t = 0
    grown = moved = 0
    for k in range(3000):
        t += int(rng.integers(1, 10))
        gyro, accel = rng.normal(size=3), rng.normal(size=3)
        capacity, start = len(window._t), window._start
        window.append(t, gyro, accel)
        moved += start > 0 and window._start == 0 and len(window._t) == capacity
        reference.append((t, gyro, accel))
        grown += len(window._t) > capacity
        span = int(rng.integers(20, 400)) if k % 500 < 250 else int(rng.integers(0, 30))  # long, then short windows
        window.drop_older(span)
        while reference[-1][0] - reference[0][0] > span:
            reference.popleft()
        assert len(window) == len(reference)
        assert window.first_t() == reference[0][0] and window.last_t() == t
        assert np.array_equal(window.last_gyro(), gyro)
        if k % 7 == 0:
            assert np.array_equal(window.times, np.array([r[0] for r in reference]))
            assert np.array_equal(window.gyro, np.array([r[1] for r in reference]))
            assert np.array_equal(window.accel, np.array([r[2] for r in reference]))
            assert window.gyro.flags.c_contiguous and window.accel.flags.c_contiguous
    assert grown >= 3 and moved > 0  # it grew from 4 rows, and slid back to the front of its arrays
