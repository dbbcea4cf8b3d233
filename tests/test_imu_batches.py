"""A replay as fast as possible hands IMU samples over in batches: the same samples in the same order,
and the estimator sees exactly what it sees one sample at a time (live)."""

import asyncio
import dataclasses

import numpy as np
import pytest

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.estimator.core.measurements import CameraFrame, GpsFix, ImuBatch, ImuRange, ImuSample
from vtolpose.estimator.filter import Estimator
from vtolpose.estimator.fusion import FusionOptions
from vtolpose.service.runtime.loop import Runtime, RuntimeOptions
from vtolpose.service.runtime.sources import FRAME_LEAD_S, ReplayClock, ReplaySource, _segments
from vtolpose.service.runtime.wiring import filter_options

from runtime_helpers import flight_samples


@pytest.fixture(scope="module")
def flight():
    return simulate_flight("landfill", 12.0, 5)


@pytest.fixture(scope="module")
def dataset(flight, tmp_path_factory) -> Dataset:
    root = tmp_path_factory.mktemp("batches") / "landfill"
    write_flight(flight, root)
    return Dataset.open(root)


def test_segments_are_imu_runs_cut_at_the_length_limit_and_single_other_samples():
    kinds = np.array([0, 0, 0, 1, 0, 0, 2, 2, 0], np.int8)
    indices = np.array([0, 1, 2, 0, 3, 4, 0, 1, 5])
    assert list(_segments(kinds, indices, 2)) == [(0, 0, 2), (0, 2, 1), (1, 0, 1), (0, 3, 2), (2, 0, 1), (2, 1, 1),
                                                  (0, 5, 1)]
    assert list(_segments(np.zeros(5, np.int8), np.arange(5), 256)) == [(0, 0, 5)]  # an IMU-only stream
    assert list(_segments(np.array([1, 0, 0], np.int8), np.array([0, 0, 1]), 1)) == [(1, 0, 1), (0, 0, 1), (0, 1, 1)]


def collect(source) -> list:
    async def read():
        return [item async for item in source]
    return asyncio.run(read())


def unbatched(items: list) -> list[tuple]:
    out = []
    for item in items:
        for sample in item.samples() if isinstance(item, ImuBatch) else (item,):
            kind = "imu" if isinstance(sample, ImuSample) else "gps"
            value = sample.gyro.tolist() + sample.accel.tolist() if kind == "imu" else sample.p_ned.tolist()
            out.append((kind, sample.t_ns, value))
    return out


@pytest.mark.parametrize("sensors", [["imu"], ["imu", "gps"]])
@pytest.mark.parametrize("start_s, stop_s", [(None, None), (2.004, 7.5), (0.0, 0.0)])
def test_a_full_speed_source_batches_the_paced_sources_samples(dataset, sensors, start_s, stop_s):
    """Batched (speed 0) and sample by sample (paced; its clock is made not to wait) give the same stream,
    start and stop times included; batches never exceed the clock's yield period; progress still moves."""
    progress_batched, progress_single = [], []
    batched = collect(ReplaySource(dataset, sensors, ReplayClock(0.0), stop_s, None, None, progress_batched.append, start_s))
    paced_clock = ReplayClock(1e12)  # paced, so one sample at a time, but never waiting
    single = collect(ReplaySource(dataset, sensors, paced_clock, stop_s, None, None, progress_single.append, start_s))
    assert all(isinstance(item, (ImuSample, GpsFix)) for item in single)
    batches = [item for item in batched if isinstance(item, ImuBatch)]
    assert batches and max(len(b) for b in batches) <= ReplayClock.YIELD_EVERY
    assert not any(isinstance(item, ImuSample) for item in batched)
    assert unbatched(batched) == unbatched(single)
    if stop_s != 0.0:
        assert progress_batched and progress_batched == sorted(progress_batched)
        # A batch reports the time of its last sample, so it is never behind the sample-by-sample report.
        assert progress_single[-1] <= progress_batched[-1] <= (stop_s if stop_s is not None else 12.0)


@pytest.mark.parametrize("stop_s", [None, 7.5])
def test_a_full_speed_source_hands_frames_over_early_and_a_paced_one_at_their_time(dataset, stop_s):
    """As fast as possible each frame comes FRAME_LEAD_S of data before its time stamp (its features are then
    extracted while the IMU's work goes on), keeping its own time; the other streams are unchanged, and frames up
    to the stop are all handed over. Paced, each frame comes at its time."""
    imu_t = dataset.imu().t_ns
    frame_t = [int(imu_t[0]) + int(k * 1e9 / 7.5) + 3_000_000 for k in range(1, 80)]
    frames = [(t, k) for k, t in enumerate(frame_t)]
    image = np.zeros((4, 4), np.uint8)
    t_end = None if stop_s is None else int(imu_t[0]) + int(stop_s * 1e9)
    expected = [t for t in frame_t if t_end is None or t <= t_end]
    for clock, early in ((ReplayClock(0.0), int(FRAME_LEAD_S * 1e9)), (ReplayClock(1e12), 0)):
        items = collect(ReplaySource(dataset, ["imu", "gps"], clock, stop_s, frames, lambda path: image))
        assert [item.t_ns for item in items if isinstance(item, CameraFrame)] == expected
        others = [item for item in items if not isinstance(item, CameraFrame)]
        assert unbatched(others) == unbatched(collect(ReplaySource(dataset, ["imu", "gps"], clock, stop_s)))
        for n, item in enumerate(items):
            if isinstance(item, CameraFrame):
                before = [x for x in items[:n] if not isinstance(x, CameraFrame)]
                after = [x for x in items[n + 1:] if not isinstance(x, CameraFrame)]
                # Everything up to (t - lead) before the frame, everything after it after (IMU first at equal times).
                assert not before or _times(before[-1])[-1] <= item.t_ns - early
                assert not after or _times(after[0])[0] > item.t_ns - early


def _times(item) -> list[int]:
    return item.t_ns.tolist() if isinstance(item, ImuBatch) else [item.t_ns]


def make_runtime(flight, imu_range: ImuRange | None = None, max_imu_buffer: int = 4096) -> tuple[Runtime, list]:
    est = Estimator(flight.calibration, filter_options(load_config(), flight.calibration.imu.noise))
    fused: list = []
    options = RuntimeOptions(fusion=FusionOptions(delay_s=0.15, max_imu_buffer=max_imu_buffer), lockstep=True,
                             imu_range=imu_range)
    runtime = Runtime(est, options, on_fused=lambda pose: fused.append(
        (pose.t_ns, *pose.p.tolist(), *pose.q.tolist(), *pose.cov9.ravel().tolist())))
    return runtime, fused


def damaged(samples: list) -> list:
    """The stream with a NaN reading, one beyond the IMU's range, and a clock step back of three samples."""
    out = list(samples)
    imu_at = [k for k, s in enumerate(out) if isinstance(s, ImuSample)]
    k = imu_at[300]
    out[k] = ImuSample(out[k].t_ns, np.full(3, np.nan), out[k].accel)
    k = imu_at[500]
    out[k] = ImuSample(out[k].t_ns, out[k].gyro * 1e4, out[k].accel)
    for j in (700, 701, 702):
        k = imu_at[j]
        out[k] = ImuSample(out[k].t_ns - 50_000_000, out[k].gyro, out[k].accel)
    return out


def batched_items(samples: list, longest: int = 37) -> list:
    """Runs of IMU samples as batches of at most ``longest``, other samples as they are."""
    items, run = [], []

    def close():
        if run:
            items.append(ImuBatch(np.array([s.t_ns for s in run], np.int64), np.array([s.gyro for s in run]),
                                  np.array([s.accel for s in run])))
            run.clear()
    for sample in samples:
        if isinstance(sample, ImuSample):
            run.append(sample)
            if len(run) == longest:
                close()
        else:
            close()
            items.append(sample)
    close()
    return items


async def feed(items):
    for item in items:
        yield item


@pytest.mark.parametrize("max_imu_buffer", [4096, 20])
def test_the_runtime_fuses_a_batch_exactly_as_its_samples(flight, max_imu_buffer):
    """Fused poses (position, attitude, covariance) and every count the same, bit for bit, with damaged
    samples in the batches (NaN, out of range, stamped in the past) and a fusion buffer a batch overflows."""
    samples = damaged(flight_samples(flight, 0.0, 12.0))
    results = []
    for items in (samples, batched_items(samples)):
        runtime, fused = make_runtime(flight, ImuRange(30.0, 160.0), max_imu_buffer)
        asyncio.run(runtime.run([feed(items)]))
        results.append((fused, runtime.est.counts_report(), runtime.fusion.counts_report(),
                        runtime.status.sensors["imu"].total))
    (fused_single, *counts_single), (fused_batched, *counts_batched) = results
    assert len(fused_single) > 500 and fused_batched == fused_single
    assert counts_batched == counts_single
    imu_counts = counts_single[0]["imu"]["rejected"]
    assert imu_counts.get("non_finite") == 1 and imu_counts.get("out_of_range") == 1
    assert counts_single[1]["imu"]["rejected"].get("time_not_increasing") == 3


def test_rows_are_screened_as_single_samples_are():
    """The compiled screen of a batch says for every row what the per-sample checks say: huge finite
    readings whose squares overflow count as non-finite, the range is on the vector's length."""
    limits = ImuRange(30.0, 160.0)
    edge = 30.0  # each axis at the range: the length is √3 × it, the limit itself (not beyond)
    rows = [([0.1, 0.2, 0.3], [0.0, 0.0, -9.8]), ([1e200, 0.0, 0.0], [0.0, 0.0, -9.8]), ([np.nan, 0.0, 0.0], [0.0] * 3),
            ([0.0, 0.0, 0.0], [np.inf, 0.0, 0.0]), ([edge, edge, edge], [0.0, 0.0, 0.0]),
            ([edge, edge, edge + 1e-3], [0.0] * 3), ([0.0] * 3, [300.0, 0.0, 0.0]), ([60.0, 0.0, 0.0], [0.0] * 3)]
    gyro, accel = np.array([g for g, _ in rows]), np.array([a for _, a in rows])
    from vtolpose.estimator.core.measurements import readings_finite, rows_finite, screened
    assert rows_finite(gyro, accel).tolist() == [readings_finite(g, a) for g, a in zip(gyro, accel)]
    assert screened(gyro, accel, limits)[0].tolist() == [limits.exceeded(g, a) for g, a in zip(gyro, accel)]
    assert screened(gyro, accel, limits)[0].tolist() == [False, False, False, False, False, True, True, True]


def test_a_replay_records_runs_of_poses_as_it_records_them_one_by_one(dataset, monkeypatch):
    """An offline replay's recorder takes the poses of a run's compiled steps as arrays (Recorder.record_run);
    its trajectory and sampled covariances are those it records from each pose (a fused-pose hook given:
    then every pose is made), bit for bit."""
    from vtolpose.service.replay.session import Recorder, replay

    in_runs = []
    record_run = Recorder.record_run
    monkeypatch.setattr(Recorder, "record_run", lambda self, run: (in_runs.append(len(run)), record_run(self, run)))
    cfg = load_config(None, {"estimator": {"heading": {"source": "gps"}}})
    runs = replay(dataset, cfg, ["imu", "gps"])
    assert sum(in_runs) > len(runs.trajectory.t_ns) // 2
    in_runs.clear()
    poses = replay(dataset, cfg, ["imu", "gps"], on_fused=lambda pose: None)
    assert not in_runs and len(runs.trajectory.t_ns) > 500 and len(runs.covariances.t_ns) > 10
    for a, b in ((runs.trajectory, poses.trajectory), (runs.covariances, poses.covariances)):
        for field in dataclasses.fields(a):
            assert np.array_equal(getattr(a, field.name), getattr(b, field.name)), field.name
