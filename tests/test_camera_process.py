"""Feature extraction in worker processes (``fusion.camera_process``): the same features as the threads,
frames through a bounded shared-memory ring, a killed worker reported and started again, the ring
unlinked at the end, and a full-speed replay that gives the same trajectory as with threads."""

import asyncio
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from multiprocessing.shared_memory import SharedMemory

import numpy as np
import pytest

from vtolpose.config import load_config
from vtolpose.estimator import FeatureOptions, FrameExtractor
from vtolpose.estimator.core.measurements import CameraFrame
from vtolpose.estimator.filter import Estimator
from vtolpose.estimator.fusion import FusionOptions
from vtolpose.service.replay.session import FrameProcessor
from vtolpose.service.runtime import camera_process
from vtolpose.service.runtime.camera_process import CameraProcesses, CameraWorkerDied
from vtolpose.service.runtime.loop import Runtime, RuntimeOptions
from vtolpose.service.runtime.sources import ReplayClock
from vtolpose.service.runtime.wiring import filter_options

from runtime_helpers import PoseList, flight_samples

SHAPE = (120, 160)


def textured(seed: int, shape: tuple[int, int] = SHAPE) -> np.ndarray:
    """A grey frame with texture every detector finds (blurred noise)."""
    import cv2

    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur((rng.random(shape) * 255).astype(np.uint8), (0, 0), 1.5)


def shifted_frames(n: int) -> list[np.ndarray]:
    """One scene moving a pixel a frame: what a tracker can follow."""
    scene = textured(7, (SHAPE[0], SHAPE[1] + n))
    return [np.ascontiguousarray(scene[:, k:k + SHAPE[1]]) for k in range(n)]


def shm_exists(name: str) -> bool:
    try:
        SharedMemory(name=name).close()
        return True
    except FileNotFoundError:
        return False


def same_features(a, b) -> bool:
    return (a.t_ns == b.t_ns and a.problem == b.problem and np.array_equal(a.keypoints, b.keypoints)
            and np.array_equal(a.descriptors, b.descriptors) and np.array_equal(a.responses, b.responses))


@pytest.mark.parametrize("options", [FeatureOptions(), FeatureOptions(track_between=2)], ids=["sift", "sift-tracked"])
def test_a_camera_process_extracts_the_features_a_camera_thread_does(options):
    import cv2

    frames = shifted_frames(5)
    local = FrameExtractor(options, SHAPE)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # as the runtime's camera threads
    try:
        expected = [local(image, 1000 + k) for k, image in enumerate(frames)]
    finally:
        cv2.setNumThreads(threads)
    processes = CameraProcesses(options, SHAPE, SHAPE, workers=1)
    processes.start()
    try:
        got = [processes.submit(image, 1000 + k).result(30) for k, image in enumerate(frames)]
    finally:
        processes.close()
    assert all(len(f) > 20 for f in got)
    assert all(same_features(a, b) for a, b in zip(got, expected))
    if options.track_between:  # the second frame was tracked (its descriptors are the first's): so was it in the worker
        first = {row.tobytes() for row in expected[0].descriptors}
        assert all(row.tobytes() in first for row in expected[1].descriptors)


def test_a_busy_camera_process_takes_no_second_frame_and_closing_unlinks_its_ring():
    processes = CameraProcesses(FeatureOptions(), SHAPE, SHAPE, workers=1)
    processes.start()
    pids = processes.pids()
    try:
        first = processes.submit(textured(1), 1)
        assert processes.submit(textured(2), 2) is None  # one frame in hand per worker: the newest is dropped
        first.result(30)
        deadline = time.monotonic() + 5
        while not processes.idle and time.monotonic() < deadline:
            time.sleep(0.01)
        assert processes.submit(textured(3), 3).result(30).t_ns == 3
        assert shm_exists(processes.ring_name)
    finally:
        processes.close()
    assert not shm_exists(processes.ring_name)
    for pid in pids:  # the workers are gone (reaped), not left behind
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


def test_a_worker_killed_with_a_frame_in_hand_fails_that_frame_and_takes_the_next():
    big = (1600, 1600)  # SIFT takes a second or so on it: the frame is still in hand when the worker is killed
    deaths = []
    processes = CameraProcesses(FeatureOptions(sift_image_scale=1.0), big, big, workers=1, on_death=deaths.append)
    processes.start()
    try:
        job = processes.submit(textured(4, big), 1)
        time.sleep(0.2)
        pid = processes.pids()[0]
        os.kill(pid, signal.SIGKILL)
        with pytest.raises(CameraWorkerDied, match=f"pid {pid}"):
            job.result(30)
        assert len(deaths) == 1 and str(pid) in str(deaths[0])
        deadline = time.monotonic() + 60
        while not processes.idle and time.monotonic() < deadline:
            time.sleep(0.05)
        assert processes.pids() != [pid] and processes.submit(textured(5, big), 2).result(60).t_ns == 2
        assert processes.report()["deaths"] == processes.report()["restarts"] == 1
    finally:
        processes.close()


@pytest.fixture(scope="module")
def flight(simulated_flight):
    return simulated_flight("landfill", 16.0, 11)


class SeenFrames(FrameProcessor):
    """The service's frame processor whose update only notes the frame (the frames are not of the flight)."""

    def __init__(self) -> None:
        super().__init__(FeatureOptions(detector="orb"), SHAPE)
        self.fused: list[int] = []

    def fusing(self, frame, features):
        assert features.problem is None and len(features) > 20
        return lambda est: self.fused.append(frame.t_ns)


def textured_flight(flight, t_from_s: float, t_to_s: float) -> list:
    items = flight_samples(flight, t_from_s, t_to_s, frames=True)
    return [CameraFrame(s.t_ns, textured(s.seq), s.seq) if isinstance(s, CameraFrame) else s for s in items]


def paced_run(runtime: Runtime, items: list, during=None):
    async def paced():
        clock = ReplayClock(1.0)
        for item in items:
            await clock.wait_until(item.t_ns)
            yield item

    async def main():
        task = asyncio.create_task(runtime.run([paced()]))
        if during is not None:
            await during()
        return await task

    return asyncio.run(main())


def in_process_runtime(flight, processor) -> Runtime:
    est = Estimator(flight.calibration, filter_options(load_config(), flight.calibration.imu.noise))
    options = RuntimeOptions(fusion=FusionOptions(delay_s=0.15), camera_process=True)
    return Runtime(est, options, outputs=[PoseList()], camera_processor=processor)


def test_a_killed_camera_worker_is_reported_and_started_again_while_poses_go_on(flight):
    processor = SeenFrames()
    runtime = in_process_runtime(flight, processor)
    items = textured_flight(flight, 0.0, 6.0)  # room for the restart on a loaded machine (~1 s)
    killed: dict[str, object] = {}

    async def kill_one():
        while runtime.camera_processes is None or not processor.fused:
            await asyncio.sleep(0.01)
        killed["ring"] = runtime.camera_processes.ring_name
        killed["pid"] = runtime.camera_processes.pids()[0]
        killed["fused"] = len(processor.fused)
        killed["poses"] = runtime.poses_published
        os.kill(killed["pid"], signal.SIGKILL)

    summary = paced_run(runtime, items, kill_one)
    assert summary.stopped_by == "end of data"
    report = summary.status["camera_process"]
    assert report["deaths"] == 1 and report["restarts"] == 1 and not report["given_up"]
    assert "camera process" in summary.status["failures"]  # reported in health
    assert str(killed["pid"]) in summary.status["failures"]["camera process"]["last"] == \
        f"CameraWorkerDied: {report['last_death']}"
    assert len(processor.fused) > killed["fused"] + 3  # the started-again worker's frames are fused
    assert summary.imu_samples == sum(hasattr(s, "gyro") for s in items)  # no sample lost to the death
    assert runtime.poses_published > killed["poses"] + 100  # and poses kept leaving
    assert not shm_exists(killed["ring"])  # the run's end unlinked the ring


def test_a_camera_that_keeps_dying_is_given_up_and_the_service_runs_on(flight, monkeypatch):
    monkeypatch.setattr(camera_process, "MAX_RESTARTS", 0)
    processor = SeenFrames()
    runtime = in_process_runtime(flight, processor)
    items = textured_flight(flight, 0.0, 3.0)

    async def kill_it():
        while runtime.camera_processes is None or not processor.fused:
            await asyncio.sleep(0.01)
        os.kill(runtime.camera_processes.pids()[0], signal.SIGKILL)

    summary = paced_run(runtime, items, kill_it)
    assert summary.stopped_by == "end of data" and summary.status["camera_process"]["given_up"]
    assert summary.status["events"]["camera_frames_unprocessed"] > 5
    assert summary.imu_samples == sum(hasattr(s, "gyro") for s in items) and runtime.poses_published > 100


def test_a_full_speed_replay_gives_the_same_trajectory_with_camera_processes(rendered_book_dir):
    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.service.replay.session import replay

    book = Dataset.open(rendered_book_dir)
    results = {}
    for in_process in (False, True):
        cfg = load_config(None, {"replay": {"camera_process": in_process, "camera_workers": 2}})
        results[in_process] = replay(book, cfg, ["imu", "camera", "gps"])
    threads, processes = results[False], results[True]
    assert len(processes.frames) == len(threads.frames) > 100
    assert [(r.t_ns, r.accepted, r.n_features) for r in processes.frames] == \
        [(r.t_ns, r.accepted, r.n_features) for r in threads.frames]
    assert np.array_equal(processes.trajectory.t_ns, threads.trajectory.t_ns)
    assert np.array_equal(processes.trajectory.p, threads.trajectory.p)
    assert np.array_equal(processes.trajectory.q, threads.trajectory.q)


def children_of(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # gone meanwhile
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def shared_memory_mapped_by(pid: int) -> set[str]:
    try:
        maps = Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return set()
    return {line.split()[-1] for line in maps.splitlines() if "/dev/shm/" in line}


def test_a_stopped_daemon_leaves_no_camera_worker_and_no_shared_memory(rendered_book_dir):
    """`vtolpose run --replay` paced with the camera (camera processes by default), stopped by SIGTERM."""
    proc = subprocess.Popen([sys.executable, "-m", "vtolpose", "run", "--replay", str(rendered_book_dir),
                             "--sensors", "imu,camera,gps", "--speed", "1"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline, rings, workers = time.monotonic() + 60, set(), []
        while not rings and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)
            workers = [pid for pid in children_of(proc.pid) if shared_memory_mapped_by(pid)]
            rings = set().union(*(shared_memory_mapped_by(pid) for pid in workers)) if workers else set()
        assert rings and all(Path(ring).exists() for ring in rings), proc.stderr.read() if proc.poll() is not None else ""
        time.sleep(1.0)  # frames flow
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "stopped by signal" in out
    assert not any(Path(ring).exists() for ring in rings)  # unlinked
    for pid in workers:  # and the workers ended with the daemon
        assert not Path(f"/proc/{pid}").exists()
