"""The rest detector: the live path (one sample at a time, in Python) and the compiled runs of samples find the
same still chunks with the same statistics, to the last bit."""

from __future__ import annotations

import numpy as np

from vtolpose.estimator.inertial.stillness import StillnessDetector, StillnessOptions

from sample_pieces import pieces

G = 9.80665


def rest_flight(seed: int, shake: slice) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """12 s at ~200 Hz: at rest, a shake over ``shake``, at rest again (times, gyro, accel)."""
    rng = np.random.default_rng(seed)
    n = 2400
    t_ns = np.cumsum(rng.integers(4_500_000, 5_500_000, n)).astype(np.int64)
    gyro = rng.normal(size=(n, 3)) * 0.003 + np.array([0.01, -0.02, 0.005])
    accel = rng.normal(size=(n, 3)) * 0.05 + np.array([0.0, 0.0, -G])
    accel[shake] += rng.normal(size=(shake.stop - shake.start, 3)) * 2.0
    return t_ns, gyro, accel


def chunks_one_by_one(detector: StillnessDetector, t_ns, gyro, accel, first: int = 0) -> list[tuple[int, object]]:
    """Each still chunk the live path reports, with its last sample's index (counted from ``first``)."""
    found = []
    for k in range(len(t_ns)):
        chunk = detector.add(int(t_ns[k]), gyro[k], accel[k], G, 0.0)
        if chunk is not None:
            found.append((first + k, chunk))
    return found


def chunks_of_a_run(detector: StillnessDetector, t_ns, gyro, accel, first: int = 0) -> list[tuple[int, object]]:
    """The same for a run of samples handed over at once (``add_run``, then ``judge`` for each ended chunk)."""
    found = []
    for end, duration, stats in detector.add_run(t_ns, gyro, accel):
        chunk = detector.judge(duration, stats, G, 0.0)
        if chunk is not None:
            found.append((first + end, chunk))
    return found


def assert_same_chunks(each: list, together: list) -> None:
    assert len(each) >= 4 and [k for k, _ in each] == [k for k, _ in together]
    for (_, a), (_, b) in zip(each, together):
        assert (a.n, a.duration_s) == (b.n, b.duration_s)
        assert np.array_equal(a.gyro_mean, b.gyro_mean) and np.array_equal(a.gyro_var_of_mean, b.gyro_var_of_mean)


def test_runs_of_samples_judge_the_chunks_one_sample_at_a_time_judges() -> None:
    t_ns, gyro, accel = rest_flight(5, slice(900, 1300))
    each = chunks_one_by_one(StillnessDetector(StillnessOptions()), t_ns, gyro, accel)
    runs, together = StillnessDetector(StillnessOptions()), []
    for start, stop in pieces(len(t_ns), np.random.default_rng(5).integers(1, 150, 200)):
        together += chunks_of_a_run(runs, t_ns[start:stop], gyro[start:stop], accel[start:stop], start)
    assert_same_chunks(each, together)


def test_runs_and_single_samples_mixed_judge_as_one_sample_at_a_time() -> None:
    """A run leaves its sums as the compiled kernel keeps them; a single sample, a judgement or the next run
    must take them from there (a declined run goes sample by sample between compiled ones)."""
    t_ns, gyro, accel = rest_flight(8, slice(1000, 1200))
    each = chunks_one_by_one(StillnessDetector(StillnessOptions()), t_ns, gyro, accel)
    rng = np.random.default_rng(8)
    mixed, together = StillnessDetector(StillnessOptions()), []
    for start, stop in pieces(len(t_ns), rng.integers(1, 120, len(t_ns))):
        take = chunks_of_a_run if rng.random() < 0.5 else chunks_one_by_one
        together += take(mixed, t_ns[start:stop], gyro[start:stop], accel[start:stop], start)
    assert_same_chunks(each, together)
