"""The IMU deltas: the live path (one sample at a time, in Python) and the compiled runs of samples give the
same steps to the last bit, so a replay fuses exactly what a live service would."""

from __future__ import annotations

import numpy as np
import pytest

from vtolpose.estimator.inertial.imu_delta import ImuDownsampler


@pytest.mark.parametrize("rate_hz", [100.0, 40.0])
def test_runs_of_samples_give_the_deltas_one_sample_at_a_time_gives(rate_hz: float) -> None:
    rng = np.random.default_rng(int(rate_hz))
    n = 600
    t_ns = np.cumsum(rng.integers(4_000_000, 6_000_000, n)).astype(np.int64)  # ~200 Hz with jitter
    gyro = rng.normal(size=(n, 3)) * 2.0
    gyro[100:140] = 0.0  # no rotation at all: the small-angle branches
    accel = rng.normal(size=(n, 3)) + np.array([0.0, 0.0, -9.81])
    one_by_one, each = ImuDownsampler(rate_hz), []
    for k in range(n):
        delta = one_by_one.add(int(t_ns[k]), gyro[k], accel[k])
        if delta is not None:
            each.append((k, delta))
    runs, together, start = ImuDownsampler(rate_hz), [], 0
    for length in rng.integers(1, 60, 100):  # runs of any length, cut anywhere in a step
        stop = min(start + int(length), n)
        found = runs.add_run(t_ns[start:stop], gyro[start:stop], accel[start:stop])
        together += [(start + end, found.delta(j)) for j, end in enumerate(found.ends)]
        start = stop
        if start == n:
            break
    assert len(each) > 50 and [k for k, _ in each] == [k for k, _ in together]
    for (_, a), (_, b) in zip(each, together):
        assert (a.t0_ns, a.t1_ns, a.dt) == (b.t0_ns, b.t1_ns, b.dt)
        assert np.array_equal(a.dtheta, b.dtheta) and np.array_equal(a.dvel, b.dvel)
    # What is left open carries on the same way.
    a, b = one_by_one.flush(), runs.flush()
    assert (a is None) == (b is None)
    if a is not None:
        assert np.array_equal(a.dtheta, b.dtheta) and np.array_equal(a.dvel, b.dvel) and a.dt == b.dt


def test_runs_and_single_samples_mixed_give_the_deltas_one_sample_at_a_time_gives() -> None:
    """A run hands its open step over in the form the next single sample (or run) takes it from."""
    rng = np.random.default_rng(3)
    n = 600
    t_ns = np.cumsum(rng.integers(4_000_000, 6_000_000, n)).astype(np.int64)
    gyro = rng.normal(size=(n, 3)) * 2.0
    accel = rng.normal(size=(n, 3)) + np.array([0.0, 0.0, -9.81])
    one_by_one, each = ImuDownsampler(40.0), []
    for k in range(n):
        delta = one_by_one.add(int(t_ns[k]), gyro[k], accel[k])
        if delta is not None:
            each.append((k, delta))
    mixed, together, start = ImuDownsampler(40.0), [], 0
    while start < n:
        stop = min(start + int(rng.integers(1, 30)), n)
        if rng.random() < 0.5:
            found = mixed.add_run(t_ns[start:stop], gyro[start:stop], accel[start:stop])
            together += [(start + end, found.delta(j)) for j, end in enumerate(found.ends)]
        else:
            for k in range(start, stop):
                delta = mixed.add(int(t_ns[k]), gyro[k], accel[k])
                if delta is not None:
                    together.append((k, delta))
        start = stop
    assert len(each) > 50 and [k for k, _ in each] == [k for k, _ in together]
    for (_, a), (_, b) in zip(each, together):
        assert (a.t0_ns, a.t1_ns, a.dt) == (b.t0_ns, b.t1_ns, b.dt)
        assert np.array_equal(a.dtheta, b.dtheta) and np.array_equal(a.dvel, b.dvel)
