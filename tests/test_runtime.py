"""The runtime's timing rules: camera work off the loop, fused at the frame's time; busy frames
dropped and counted; lock-step replays deterministic; the trajectory file complete at the end."""

import asyncio
import threading
from concurrent.futures import ThreadPoolExecutor
import time

import numpy as np
import pytest

from vtolpose.config import load_config
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.files.tum import read_tum
from vtolpose.estimator.filter import Estimator
from vtolpose.estimator.fusion import FusionOptions
from vtolpose.estimator.core.measurements import CameraFrame, GpsFix, ImuSample
from vtolpose.service.outputs.trajectory_file import TrajectoryFile
from vtolpose.service.runtime.loop import Runtime, RuntimeOptions
from vtolpose.service.runtime.sources import ReplayClock
from vtolpose.service.runtime.wiring import filter_options

from runtime_helpers import PoseList, flight_samples


@pytest.fixture(scope="module")
def flight():
    return simulate_flight("landfill", 16.0, 11)


def samples(flight, t_from_s: float, t_to_s: float, frames: bool = True):
    return flight_samples(flight, t_from_s, t_to_s, frames)


def make_runtime(flight, processor, lockstep=False, trajectory=None) -> Runtime:
    est = Estimator(flight.calibration, filter_options(load_config(), flight.calibration.imu.noise))
    options = RuntimeOptions(fusion=FusionOptions(delay_s=0.15), lockstep=lockstep)
    return Runtime(est, options, outputs=[PoseList()], camera_processor=processor, trajectory=trajectory)


async def paced(items, speed: float):
    clock = ReplayClock(speed)
    for item in items:
        await clock.wait_until(item.t_ns)
        yield item


def run(runtime: Runtime, items, speed: float):
    return asyncio.run(runtime.run([paced(items, speed)]))


def test_camera_work_does_not_hold_up_poses_and_is_fused_at_the_frame_time(flight):
    warm = samples(flight, 0.0, 12.0, frames=False)
    live = samples(flight, 12.0, 14.0)
    applied, during = [], []

    def extract(frame):
        before = runtime.poses_published
        time.sleep(0.06)  # feature extraction: 60 ms, within the 150 ms horizon
        during.append(runtime.poses_published - before)
        return lambda est: applied.append((frame.t_ns, est.counts["imu"].received, threading.current_thread().name))

    runtime = make_runtime(flight, extract)
    for s in warm:  # the filter starts and aligns at full speed
        runtime.handle(s)
    summary = run(runtime, live, speed=1.0)
    n_frames = sum(isinstance(s, CameraFrame) for s in live)
    dropped = runtime.status.events.get("camera_frames_dropped_busy", 0)  # only on a badly loaded machine
    assert len(applied) == n_frames - dropped == runtime.fusion.counts["camera"].used and dropped <= 2
    assert min(during) >= 3  # 60 ms at 125 Hz: poses kept leaving meanwhile
    # Fused at the frame's own time: the filter had consumed every IMU sample up to it, and none after it.
    imu_times = np.array([s.t_ns for s in warm + live if isinstance(s, ImuSample)])
    assert [consumed for _, consumed, _ in applied] == [int(np.sum(imu_times <= t)) for t, _, _ in applied]
    assert all(t not in imu_times for t, _, _ in applied)  # between samples: one sample early or late shows
    assert {name for *_, name in applied} == {threading.main_thread().name}  # applied on the loop, in order
    assert runtime.fusion.counts["camera"].rejected == {} and summary.stopped_by == "end of data"


def test_slow_camera_work_is_dropped_or_too_late_never_queued(flight):
    live = samples(flight, 0.0, 2.0)

    def extract(frame):
        time.sleep(0.25)  # slower than the frame period and longer than the horizon
        return lambda est: None

    runtime = make_runtime(flight, extract)
    run(runtime, live, speed=1.0)
    events, counts = runtime.status.events, runtime.fusion.counts["camera"]
    assert events["camera_frames_dropped_busy"] > 0
    # Results that come back after the horizon has passed their frame are refused (the last one,
    # finished during shutdown when the horizon stops, may still be fused).
    assert set(counts.rejected) == {"too_late"} and counts.rejected["too_late"] >= counts.received - 1 > 0


def test_lockstep_replay_waits_for_camera_work_and_is_deterministic(flight, tmp_path):
    items = samples(flight, 0.0, 4.5)
    trajectories = []
    for run_number in range(2):
        applied = []

        def extract(frame, applied=applied):
            time.sleep(0.02 if run_number == 0 else 0.001)  # different machine speeds, same result
            return lambda est: applied.append(frame.t_ns)

        path = tmp_path / f"traj{run_number}.txt"
        runtime = make_runtime(flight, extract, lockstep=True, trajectory=TrajectoryFile(path))
        run(runtime, items, speed=0.0)
        assert applied == [s.t_ns for s in items if isinstance(s, CameraFrame)]
        trajectories.append(path.read_bytes())
    assert trajectories[0] == trajectories[1]
    t, p, q = read_tum(tmp_path / "traj0.txt")
    assert len(t) > 80 and np.all(np.diff(t) > 0)


def test_sensor_time_offsets_are_applied_where_samples_enter(flight):
    """A GPS 120 ms late and a camera 37 ms late are fused at the times they really measured."""
    from dataclasses import replace

    from vtolpose.drivers.simulator.render import default_camera

    cal = replace(flight.calibration, gps=replace(flight.calibration.gps, time_offset_s=-0.12),
                  camera=replace(default_camera(), time_offset_s=-0.037))
    est = Estimator(cal, filter_options(load_config(), cal.imu.noise))
    seen = []
    runtime = Runtime(est, RuntimeOptions(fusion=FusionOptions(delay_s=0.5)),
                      camera_processor=lambda frame: seen.append(frame.t_ns))
    t = int(flight.imu.t_ns[0]) + 1_000_000_000
    runtime.handle(ImuSample(t, np.zeros(3), np.array([0.0, 0.0, -9.8])))
    runtime.handle(GpsFix(t, np.zeros(3), 1.0, 1.4))
    assert [entry[0] for entry in runtime.fusion._pending] == [t - 120_000_000]

    async def one_frame():
        runtime._executor = ThreadPoolExecutor(1)
        runtime._on_camera(CameraFrame(t, np.zeros((4, 4), np.uint8)))
        await asyncio.gather(*[f for _, f in runtime._camera_jobs])

    asyncio.run(one_frame())
    assert seen == [t - 37_000_000]


def test_camera_work_yields_the_cpu_to_the_pose_path_in_paced_runs(flight):
    """Live-paced: camera threads are niced and OpenCV runs single-threaded inside them (so SIFT cannot
    take both cores from the loop); the process's OpenCV setting is restored afterwards."""
    import os

    import cv2

    seen = []

    def processor(frame):
        seen.append((os.getpriority(os.PRIO_PROCESS, threading.get_native_id()), cv2.getNumThreads()))
        return None

    before = cv2.getNumThreads()
    cv2.setNumThreads(2)  # as on a 2-core computer, whatever this one has
    try:
        run(make_runtime(flight, processor), samples(flight, 0.0, 1.0), speed=50.0)
        assert cv2.getNumThreads() == 2  # the process's setting back after the run
    finally:
        cv2.setNumThreads(before)
    assert seen and all(nice == 10 and threads == 1 for nice, threads in seen)
    seen.clear()
    cv2.setNumThreads(2)
    try:
        run(make_runtime(flight, processor, lockstep=True), samples(flight, 0.0, 1.0), speed=0.0)
    finally:
        cv2.setNumThreads(before)
    assert seen and all(threads == 2 for _, threads in seen)  # full-speed replays keep OpenCV's pool


def test_the_pose_history_is_kept_for_outputs_only(flight):
    """The history answers queries through an output; an offline replay without one keeps none
    (and no output predictor), so the same fused trajectory costs less."""
    items = samples(flight, 0.0, 8.0, frames=False)
    fused = {}
    for outputs in ([PoseList()], []):
        est = Estimator(flight.calibration, filter_options(load_config(), flight.calibration.imu.noise))
        seen = []
        runtime = Runtime(est, RuntimeOptions(fusion=FusionOptions(delay_s=0.15), lockstep=True), outputs=outputs,
                          on_fused=lambda pose, seen=seen: seen.append((pose.t_ns, *pose.p.tolist())))
        run(runtime, items, 0.0)
        assert runtime.keep_history is bool(outputs) and runtime.fusion.predict is bool(outputs)
        assert (len(runtime.history) > 0) is bool(outputs)
        fused[bool(outputs)] = seen
    assert fused[True] == fused[False] and len(fused[True]) > 100


def test_latency_probes_time_each_outputs_publish_within_the_handling(flight):
    """Measuring, the runtime times each output's publish call by name (the bench's "of which" rows): a slow
    output's share shows as its own, inside the loop's handling; not measuring, nothing is timed."""

    class SlowOutput(PoseList):
        name = "slow"

        def publish(self, pose) -> None:
            time.sleep(0.002)
            super().publish(pose)

    est = Estimator(flight.calibration, filter_options(load_config(), flight.calibration.imu.noise))
    fast, slow = PoseList(), SlowOutput()
    runtime = Runtime(est, RuntimeOptions(fusion=FusionOptions(delay_s=0.15), measure_latency=True), outputs=[fast])
    runtime.outputs.append(slow)  # outputs join after construction, as the daemon adds them
    for s in samples(flight, 0.0, 11.0, frames=False):
        runtime.handle(s)
    published = runtime.poses_published
    assert published > 100 and len(fast.poses) == len(slow.poses) == published
    assert {name: len(probe) for name, probe in runtime.publishing.items()} == {"list": published, "slow": published}
    slow_p50, = runtime.publishing["slow"].percentiles_ms(50)
    fast_p50, = runtime.publishing["list"].percentiles_ms(50)
    handling_p50, = runtime.handling.percentiles_ms(50)
    assert 2.0 <= slow_p50 <= handling_p50 and fast_p50 < 1.0
    quiet = Runtime(Estimator(flight.calibration, filter_options(load_config(), flight.calibration.imu.noise)),
                    RuntimeOptions(fusion=FusionOptions(delay_s=0.15)), outputs=[PoseList()])
    for s in samples(flight, 0.0, 1.0, frames=False):
        quiet.handle(s)
    assert quiet.publishing is None and quiet.handling is None


def test_outputs_are_handed_the_next_poses_covariance_after_a_pose_left(flight):
    """After each pose, an output with ``prepare`` gets the covariance the fusion core has ready for the next pose
    (FusionCore.next_pose_cov): the pose that follows carries that very array unless a measurement was fused in
    between, so the Zenoh output writes its text off the pose path. A failing ``prepare`` is that output's only."""

    class Preparing(PoseList):
        name = "preparing"

        def __init__(self) -> None:
            super().__init__()
            self.prepared = None
            self.hits = 0

        def prepare(self, pose_cov) -> None:
            self.prepared = pose_cov

        def publish(self, pose) -> None:
            self.hits += pose.pose_cov is self.prepared
            super().publish(pose)

    class Broken(PoseList):
        name = "broken"

        def prepare(self, pose_cov) -> None:
            raise RuntimeError("prepare broke")

    est = Estimator(flight.calibration, filter_options(load_config(), flight.calibration.imu.noise))
    preparing, broken = Preparing(), Broken()
    runtime = Runtime(est, RuntimeOptions(fusion=FusionOptions(delay_s=0.15)), outputs=[preparing, broken])
    items = samples(flight, 0.0, 12.0, frames=False)
    for s in items:
        runtime.handle(s)
    published, fixes = runtime.poses_published, sum(isinstance(s, GpsFix) for s in items)
    assert published > 500 and len(preparing.poses) == len(broken.poses) == published
    # Every pose but those after a fix (its update changes the state: the next covariance is made afresh).
    assert published - fixes - 5 <= preparing.hits < published
    assert runtime.failures.report()["output broken"]["failures"] == published  # each one counted, no pose lost


def test_the_bare_sends_of_the_latency_bench_reach_their_peers():
    """The latency bench's floor (a bare datagram and a bare Zenoh put) is timed on sends that arrive: a peer in
    another process for each, on loopback; a put that nobody subscribes to would cost less than a real one."""
    from vtolpose.service.bench.runtime import bare_sends_us

    udp_us, put_us, udp_got, put_got = bare_sends_us(245, 900, count=200)
    assert 0.0 < udp_us < 10_000.0 and 0.0 < put_us < 10_000.0
    assert udp_got == 200 and put_got >= 190  # the first puts may race the subscriber's interest
