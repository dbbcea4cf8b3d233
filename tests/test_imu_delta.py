"""The IMU deltas: the live path (one sample at a time, in Python) and the compiled runs of samples give the
same steps to the last bit, so a replay fuses exactly what a live service would."""

from __future__ import annotations

import numpy as np
import pytest

from vtolpose.estimator.inertial.imu_delta import ImuDownsampler

from sample_pieces import pieces


def imu_samples(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """600 samples at ~200 Hz with jitter (times, gyro, accel), 40 of them without any rotation."""
    rng = np.random.default_rng(seed)
    n = 600
    t_ns = np.cumsum(rng.integers(4_000_000, 6_000_000, n)).astype(np.int64)
    gyro = rng.normal(size=(n, 3)) * 2.0
    gyro[100:140] = 0.0  # no rotation at all: the small-angle branches
    accel = rng.normal(size=(n, 3)) + np.array([0.0, 0.0, -9.81])
    return t_ns, gyro, accel


def deltas_one_by_one(downsampler: ImuDownsampler, t_ns, gyro, accel, first: int = 0) -> list[tuple[int, object]]:
    """Each delta the live path completes, with its last sample's index (counted from ``first``)."""
    found = []
    for k in range(len(t_ns)):
        delta = downsampler.add(int(t_ns[k]), gyro[k], accel[k])
        if delta is not None:
            found.append((first + k, delta))
    return found


def deltas_of_a_run(downsampler: ImuDownsampler, t_ns, gyro, accel, first: int = 0) -> list[tuple[int, object]]:
    """The same for a run of samples handed over at once (``add_run``)."""
    found = downsampler.add_run(t_ns, gyro, accel)
    return [(first + end, found.delta(j)) for j, end in enumerate(found.ends)]


def assert_same_deltas(each: list, together: list) -> None:
    assert len(each) > 50 and [k for k, _ in each] == [k for k, _ in together]
    for (_, a), (_, b) in zip(each, together):
        assert (a.t0_ns, a.t1_ns, a.dt) == (b.t0_ns, b.t1_ns, b.dt)
        assert np.array_equal(a.dtheta, b.dtheta) and np.array_equal(a.dvel, b.dvel)


@pytest.mark.parametrize("rate_hz", [100.0, 40.0])
def test_runs_of_samples_give_the_deltas_one_sample_at_a_time_gives(rate_hz: float) -> None:
    t_ns, gyro, accel = imu_samples(int(rate_hz))
    one_by_one, runs = ImuDownsampler(rate_hz), ImuDownsampler(rate_hz)
    each = deltas_one_by_one(one_by_one, t_ns, gyro, accel)
    together = []
    # Runs of any length, cut anywhere in a step.
    for start, stop in pieces(len(t_ns), np.random.default_rng(int(rate_hz)).integers(1, 60, 100)):
        together += deltas_of_a_run(runs, t_ns[start:stop], gyro[start:stop], accel[start:stop], start)
    assert_same_deltas(each, together)
    # What is left open carries on the same way.
    a, b = one_by_one.flush(), runs.flush()
    assert (a is None) == (b is None)
    if a is not None:
        assert np.array_equal(a.dtheta, b.dtheta) and np.array_equal(a.dvel, b.dvel) and a.dt == b.dt


def test_runs_and_single_samples_mixed_give_the_deltas_one_sample_at_a_time_gives() -> None:
    """A run hands its open step over in the form the next single sample (or run) takes it from."""
    t_ns, gyro, accel = imu_samples(3)
    each = deltas_one_by_one(ImuDownsampler(40.0), t_ns, gyro, accel)
    rng = np.random.default_rng(3)
    mixed, together = ImuDownsampler(40.0), []
    for start, stop in pieces(len(t_ns), rng.integers(1, 30, len(t_ns))):
        take = deltas_of_a_run if rng.random() < 0.5 else deltas_one_by_one
        together += take(mixed, t_ns[start:stop], gyro[start:stop], accel[start:stop], start)
    assert_same_deltas(each, together)


def deltas_to_time(downsampler: ImuDownsampler, t_ns: int, after, compiled: bool) -> list[tuple]:
    """The deltas that bring the state to a measurement at ``t_ns``: ``flush`` then ``hold``, or ``to_time``."""
    if compiled:
        times, dts, deltas = downsampler.to_time(t_ns, after)
        return [(*map(int, times[j]), float(dts[j]), deltas[j, 0:3].tolist(), deltas[j, 3:6].tolist())
                for j in range(len(dts))]
    made = (downsampler.flush(), downsampler.hold(t_ns, after))
    return [(d.t0_ns, d.t1_ns, d.dt, d.dtheta.tolist(), d.dvel.tolist()) for d in made if d is not None]


@pytest.mark.parametrize("interpolated", [True, False])
def test_the_compiled_step_to_a_measurements_time_is_flush_then_hold(interpolated: bool) -> None:
    """``to_time`` (one compiled call) gives the deltas ``flush`` and ``hold`` give, bit for bit, with the
    reading interpolated towards the next sample or held, and leaves the state the next samples (one by one
    or in runs) carry on from: measurements between samples, two at one time, one at a sample's time."""
    t_ns, gyro, accel = imu_samples(5)
    rng = np.random.default_rng(5)
    python, compiled = ImuDownsampler(40.0), ImuDownsampler(40.0)
    made = {False: [], True: []}
    checked = 0
    for start, stop in pieces(len(t_ns), rng.integers(1, 25, len(t_ns))):
        for downsampler, is_compiled in ((python, False), (compiled, True)):
            take = deltas_of_a_run if is_compiled and rng.random() < 0.7 else deltas_one_by_one
            made[is_compiled] += [(k, d.t0_ns, d.t1_ns, d.dt, d.dtheta.tolist(), d.dvel.tolist())
                                  for k, d in take(downsampler, t_ns[start:stop], gyro[start:stop], accel[start:stop], start)]
        if stop >= len(t_ns):
            break
        last = int(t_ns[stop - 1])
        between = last + int((int(t_ns[stop]) - last) * rng.uniform(0.1, 0.9))
        after = (int(t_ns[stop]), gyro[stop], accel[stop]) if interpolated else None
        for t in (between, between, last) if rng.random() < 0.3 else (between,):  # twice at one time; at the sample's own
            a = deltas_to_time(python, t, after, False)
            b = deltas_to_time(compiled, t, after, True)
            assert a == b
            checked += len(a)
    assert checked > 40 and len(made[False]) > 50
    assert made[False] == made[True]
