"""The replay's recorder keeps a run's poses as the run hands them over (arrays, not rows): the trajectory and the
covariance samples it gives are those of the same replay recorded pose by pose, to the last bit."""

from __future__ import annotations

import numpy as np
import pytest

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.estimator.fusion import FusedRun
from vtolpose.service.replay.session import Recorder, replay


@pytest.mark.parametrize("variant", ["biases", "thesis"])
def test_runs_recorded_whole_read_back_as_the_poses_one_by_one(flight_folder, variant):
    dataset = Dataset.open(flight_folder("book", 30.0, 2))
    cfg = load_config(None, {"estimator": {"variant": variant}})
    whole = replay(dataset, cfg, ["imu", "gps"])  # runs reach the recorder as FusedRun
    single = replay(dataset, cfg, ["imu", "gps"], on_fused=lambda pose: None)  # every pose through record()
    a, b = whole.trajectory, single.trajectory
    assert len(a.t_ns) == len(b.t_ns) > 1500 and a.t_ns.dtype == b.t_ns.dtype == np.int64
    for name in ("t_ns", "p", "v", "q", "unscored"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert a.unscored.dtype == bool
    ca, cb = whole.covariances, single.covariances
    assert len(ca.t_ns) == len(cb.t_ns) > 20
    for name in ("t_ns", "p", "q", "cov"):
        assert np.array_equal(getattr(ca, name), getattr(cb, name)), name


def test_an_empty_recording_gives_empty_arrays_of_the_right_shapes():
    trajectory = Recorder(int(1e8)).trajectory()
    assert trajectory.t_ns.shape == (0,) and trajectory.p.shape == (0, 3) and trajectory.q.shape == (0, 4)
    assert trajectory.unscored.dtype == bool


def _run(t_ns: list[int], positioned: bool) -> FusedRun:
    """A run of steps whose poses are worth scoring only with a position (``positioned``)."""
    m = len(t_ns)
    rng = np.random.default_rng(m)
    covs = np.stack([np.eye(15) * (1.0 + k) for k in range(m)])
    return FusedRun(np.array(t_ns, np.int64), rng.normal(size=(m, 3)), rng.normal(size=(m, 3)), rng.normal(size=(m, 4)),
                    np.zeros((m, 3)), list(range(m)), np.zeros(3), covs, np.full(3, 1e-6), True, True, positioned, 0,
                    [100] * m, False, None)


def test_runs_before_the_position_are_unscored_and_never_sampled_for_covariance():
    """Runs kept as blocks keep their poses' scoring flag, beside single poses in their places; the covariance is
    sampled every period from the first scored pose, across runs, as pose by pose."""
    recorder = Recorder(int(25e6))
    runs = [_run([0, 10_000_000], False), _run([20_000_000, 30_000_000, 40_000_000, 70_000_000], True),
            _run([80_000_000], True)]
    recorder.record_run(runs[0])
    recorder.record_run(runs[1])
    recorder.record_run(runs[2])
    trajectory = recorder.trajectory()
    assert trajectory.unscored.tolist() == [True, True, False, False, False, False, False]
    assert recorder.covariance_samples().t_ns.tolist() == [20_000_000, 70_000_000]  # 45 ms and on: 70 ms, then 95 ms
    assert np.array_equal(recorder.covariance_samples().cov[1], runs[1].pose_cov(3))


def test_the_columns_grow_past_their_first_room_keeping_every_pose_in_order():
    """Runs and single poses, alternately, past the recorder's first room twice: every pose where it came."""
    recorder = Recorder(int(1e9))
    runs, t0 = [], 0
    for k in range(300):  # 300 runs of 1..59 poses, every other one recorded pose by pose
        m = 1 + (7 * k) % 59
        run = _run([t0 + 1_000_000 * i for i in range(m)], k % 5 != 0)
        t0 += 1_000_000 * m
        runs.append(run)
        if k % 2:
            for pose in run.poses():
                recorder.record(pose)
        else:
            recorder.record_run(run)
    trajectory = recorder.trajectory()
    assert len(trajectory.t_ns) == sum(len(run) for run in runs) > 2 * 4096
    for name in ("t_ns", "p", "v", "q"):
        assert np.array_equal(getattr(trajectory, name), np.concatenate([getattr(run, name) for run in runs])), name
    assert trajectory.unscored.tolist() == [not run.position_initialized for run in runs for _ in range(len(run))]
