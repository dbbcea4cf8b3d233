"""The rest detector: the live path (one sample at a time, in Python) and the compiled runs of samples find the
same still chunks with the same statistics, to the last bit."""

from __future__ import annotations

import numpy as np

from vtolpose.estimator.inertial.stillness import StillnessDetector, StillnessOptions

G = 9.80665


def test_runs_of_samples_judge_the_chunks_one_sample_at_a_time_judges() -> None:
    rng = np.random.default_rng(5)
    n = 2400  # 12 s at 200 Hz: at rest, a shake in the middle, at rest again
    t_ns = np.cumsum(rng.integers(4_500_000, 5_500_000, n)).astype(np.int64)
    gyro = rng.normal(size=(n, 3)) * 0.003 + np.array([0.01, -0.02, 0.005])
    accel = rng.normal(size=(n, 3)) * 0.05 + np.array([0.0, 0.0, -G])
    accel[900:1300] += rng.normal(size=(400, 3)) * 2.0
    one_by_one, each = StillnessDetector(StillnessOptions()), []
    for k in range(n):
        chunk = one_by_one.add(int(t_ns[k]), gyro[k], accel[k], G, 0.0)
        if chunk is not None:
            each.append((k, chunk))
    runs, together, start = StillnessDetector(StillnessOptions()), [], 0
    for length in rng.integers(1, 150, 200):
        stop = min(start + int(length), n)
        for end, duration, stats in runs.add_run(t_ns[start:stop], gyro[start:stop], accel[start:stop]):
            chunk = runs.judge(duration, stats, G, 0.0)
            if chunk is not None:
                together.append((start + end, chunk))
        start = stop
        if start == n:
            break
    assert len(each) >= 4 and [k for k, _ in each] == [k for k, _ in together]
    for (_, a), (_, b) in zip(each, together):
        assert (a.n, a.duration_s) == (b.n, b.duration_s)
        assert np.array_equal(a.gyro_mean, b.gyro_mean) and np.array_equal(a.gyro_var_of_mean, b.gyro_var_of_mean)


def test_runs_and_single_samples_mixed_judge_as_one_sample_at_a_time() -> None:
    """A run leaves its sums as the compiled kernel keeps them; a single sample, a judgement or the next run
    must take them from there (a declined run goes sample by sample between compiled ones)."""
    rng = np.random.default_rng(8)
    n = 2400
    t_ns = np.cumsum(rng.integers(4_500_000, 5_500_000, n)).astype(np.int64)
    gyro = rng.normal(size=(n, 3)) * 0.003 + np.array([0.01, -0.02, 0.005])
    accel = rng.normal(size=(n, 3)) * 0.05 + np.array([0.0, 0.0, -G])
    accel[1000:1200] += rng.normal(size=(200, 3)) * 2.0
    one_by_one, each = StillnessDetector(StillnessOptions()), []
    for k in range(n):
        chunk = one_by_one.add(int(t_ns[k]), gyro[k], accel[k], G, 0.0)
        if chunk is not None:
            each.append((k, chunk))
    mixed, together, start = StillnessDetector(StillnessOptions()), [], 0
    while start < n:
        stop = min(start + int(rng.integers(1, 120)), n)
        if rng.random() < 0.5:
            for end, duration, stats in mixed.add_run(t_ns[start:stop], gyro[start:stop], accel[start:stop]):
                chunk = mixed.judge(duration, stats, G, 0.0)
                if chunk is not None:
                    together.append((start + end, chunk))
        else:
            for k in range(start, stop):
                chunk = mixed.add(int(t_ns[k]), gyro[k], accel[k], G, 0.0)
                if chunk is not None:
                    together.append((k, chunk))
        start = stop
    assert len(each) >= 4 and [k for k, _ in each] == [k for k, _ in together]
    for (_, a), (_, b) in zip(each, together):
        assert (a.n, a.duration_s) == (b.n, b.duration_s)
        assert np.array_equal(a.gyro_mean, b.gyro_mean) and np.array_equal(a.gyro_var_of_mean, b.gyro_var_of_mean)
