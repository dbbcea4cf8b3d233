"""The replay's recorder keeps a run's poses as the run hands them over (arrays, not rows): the trajectory and the
covariance samples it gives are those of the same replay recorded pose by pose, to the last bit."""

from __future__ import annotations

import numpy as np
import pytest

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
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
