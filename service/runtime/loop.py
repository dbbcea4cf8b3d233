"""The onboard runtime: sources → fusion → outputs on one asyncio loop, for live runs and replays alike.

Timing rules (spec "Fusion order"):
- An IMU sample is handled the moment it arrives: it goes into the fusion core, the pose
  predicted to it is published (ODOMETRY, Zenoh) and stored in the history. Nothing on this
  path waits for anything else.
- Camera work (feature extraction) runs in a thread pool off the loop, or (``camera_process``)
  in worker processes fed through shared memory, so that it never holds the loop's interpreter;
  its result becomes a measurement queued at the frame's own timestamp, fused when the delayed
  horizon reaches it. One frame at most per worker is in flight: a frame arriving while all
  workers are busy is dropped and counted, never queued without bound. With ``update_thread``
  (live runs) an advance that fuses a frame, or checks the covariance of a state with a map, runs on
  the fusion thread (``fusion_thread``) while the poses go on from a detached prediction; what
  arrives meanwhile waits for it, in order.
- In lock-step mode (a replay at full speed) the loop waits for a frame's features before the
  horizon passes the frame, so a replay gives the same result however fast the machine is.
Shutdown (SIGINT/SIGTERM, the end of a replay, a duration): sources are stopped, camera work
finishes, the fusion core is flushed so the trajectory file is complete, links are closed.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import os
import threading
import time
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any, AsyncIterator, Callable, Protocol, Sequence

import numpy as np

from vtolpose.estimator import (
    Apply, CameraFrame, COV, Estimator, FixedLagSmoother, FrameFeatures, FusedRun, FusionCore, FusionOptions, GpsFix,
    ImuBatch, ImuRange, ImuSample, OutputPose, P, PoseHistory, Q, readings_finite, ROW, screened, SmoothedPose, V,
)
from vtolpose.service.outputs.trajectory_file import TrajectoryFile
from vtolpose.service.outputs.zenoh_answers import HistoryFeed
from vtolpose.service.runtime.camera_process import CAMERA_NICE, CameraProcesses, CameraWorkerDied
from vtolpose.service.runtime.fusion_thread import FusionThread
from vtolpose.service.runtime.step_taps import StepTaps
from vtolpose.service.runtime.status import (FailureBook, LatencyProbe, StatusTracker, pose_problem, pose_quality,
                                             stopped_within)

log = logging.getLogger(__name__)

# Feature extraction for one frame, run on a worker thread. Returns the measurement to fuse at
# the frame's time (e.g. ``lambda est: est.process_features(features)``) or None.
CameraProcessor = Callable[[CameraFrame], Apply | None]


class PoseOutput(Protocol):
    """An output link. ``publish`` is on the hot path and must not block."""

    name: str
    def open(self) -> None: ...
    def publish(self, pose: OutputPose) -> Any: ...
    # Optional: ``prepare(pose_cov)``, after a pose left, the covariance the next one will carry
    # (FusionCore.next_pose_cov, or None), for an output that writes its part ahead (Zenoh).
    def publish_status(self, status: dict[str, Any]) -> None: ...
    async def serve(self, stop: asyncio.Event) -> None: ...
    def close(self) -> None: ...


def set_thread_priority(priority: int | None) -> bool:
    """SCHED_FIFO at ``priority`` for the calling thread (threads it starts inherit it), None: normal.

    A flight computer runs its estimator above everything else so that other processes cannot
    delay a pose; it needs CAP_SYS_NICE (in Docker: --cap-add SYS_NICE --ulimit rtprio=99).
    Refused: a warning, and the run continues at normal priority.
    """
    try:
        if priority is None:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        else:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (AttributeError, OSError) as exc:
        if priority is not None:
            log.warning("real-time priority %d refused (%s); running at normal priority", priority, exc)
        return False


def background_thread_priority() -> None:
    """For camera worker threads: normal scheduling (never the loop's SCHED_FIFO), niced so that the
    loop wins a contended core. Raising one's own nice needs no privilege (Linux: per thread)."""
    set_thread_priority(None)
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), CAMERA_NICE)
    except (AttributeError, OSError) as exc:
        log.debug("camera thread nice %d refused: %s", CAMERA_NICE, exc)


@dataclass(slots=True)
class RuntimeOptions:
    fusion: FusionOptions = field(default_factory=FusionOptions)
    history_s: float = 120.0
    camera_workers: int = 1
    camera_process: bool = False  # extraction in worker processes (frames in shared memory), not threads
    lockstep: bool = False  # replay at full speed: wait for camera work at the horizon (deterministic)
    status_period_s: float = 1.0
    measure_latency: bool = False
    realtime_priority: int | None = None  # SCHED_FIFO priority for the loop and the device readers
    imu_range: ImuRange | None = None  # plausibility: readings beyond it are refused where they enter
    update_thread: bool = False  # live runs with a camera: a frame's update on a thread, the poses go on (fusion_thread)


@dataclass
class RunSummary:
    imu_samples: int
    poses_published: int
    trajectory_lines: int
    wall_s: float
    data_s: float
    stopped_by: str
    latency_ms: dict[str, float]
    status: dict[str, Any]
    trajectory_error: str | None = None  # a write to the trajectory file failed (a full disk): it is incomplete
    incomplete: list[str] = field(default_factory=list)  # each requested file output that is incomplete, and why


class Runtime:
    """Owns the fusion core, the pose history and the outputs; see the module docstring for timing."""

    def __init__(
        self,
        estimator: Estimator,
        options: RuntimeOptions | None = None,
        outputs: Sequence[PoseOutput] = (),
        camera_processor: CameraProcessor | None = None,
        trajectory: TrajectoryFile | None = None,
        on_fused: Callable[[OutputPose], None] | None = None,
        taps: StepTaps | None = None,
        on_fused_run: Callable[[FusedRun], None] | None = None,
    ) -> None:
        """``taps``: who sees the filter's steps (the fixed-lag smoother, a replay's step files); the estimator
        must have been built with their recorder. ``on_fused_run``: takes a run's fused poses at once in place
        of ``on_fused`` for each, where nothing else here wants them one by one (history, trajectory file)."""
        if taps is not None and estimator.recorder is not taps.recorder:
            raise ValueError("the estimator must be built with the step taps' recorder (Estimator(..., recorder=))")
        self.options = opts = options or RuntimeOptions()
        self.fused_hook = on_fused  # sees every fused pose (a replay's recorder)
        self.fused_run_hook = on_fused_run  # or, where it may, a run of them at once
        self._close_errors: dict[str, str] = {}  # file outputs whose close failed: name -> why
        # Stamps enter on the IMU clock: each sensor's calibrated offset is added here, before the
        # fusion horizon orders them (so a late camera is fused at the time it really saw).
        cal = estimator.calibration
        self._gps_offset_ns = int(round(cal.gps.time_offset_s * 1e9))
        self._camera_offset_ns = int(round(cal.camera.time_offset_s * 1e9)) if cal.camera is not None else 0
        self.est = estimator
        self.fusion = FusionCore(estimator, opts.fusion, on_fused=self._on_fused, on_fused_run=self._on_fused_run)
        self.history = PoseHistory(opts.history_s)
        self.history_lock = threading.Lock()  # queries read the history on Zenoh's threads
        self.keep_history = True  # run() turns it off when there are no outputs to answer from it
        self.history_feed: HistoryFeed | None = None  # a copy of the history elsewhere (the query process) gets every change
        self.outputs = list(outputs)
        self.camera_processor = camera_processor
        self.trajectory = trajectory
        self.status = StatusTracker()
        self.failures = FailureBook()  # outputs, sources, the trajectory file: isolated, counted, reported
        # Latency from a sample's hand-over by its source to both outputs returning, and the part of
        # it spent in this loop's handling (the rest is waiting to be scheduled).
        self.latency = LatencyProbe() if opts.measure_latency else None
        self.handling = LatencyProbe() if opts.measure_latency else None
        # And each output's own share of the handling (its publish call), by name (outputs join after this).
        self.publishing: defaultdict[str, LatencyProbe] | None = defaultdict(LatencyProbe) if opts.measure_latency else None
        self.origin: Callable[[], tuple[float, float, float] | None] = lambda: None  # geodetic origin of NED
        self.last_pose: OutputPose | None = None
        self.recorder: Any | None = None  # set by `vtolpose run --record`
        self.sample_taps: list[Callable[[Any], None]] = []  # see every raw sample as it arrives (MCAP, Foxglove)
        self.poses_published = 0
        # Fixed-lag smoothing (the taps' smoother): smoothed poses replace filtered ones in the history.
        self.smoother: FixedLagSmoother | None = taps.smoother if taps is not None else None
        self.smoothed_hook: Callable[[list[SmoothedPose]], None] | None = None  # sees them too (a replay's report)
        self._records = taps is not None and taps.recorder is not None
        if taps is not None:
            taps.report_failures_to(self.failures.record)
        self._smoothing_finished = False
        self._executor: ThreadPoolExecutor | None = None
        self._fusion_thread: FusionThread | None = None  # run() makes one for live runs with a camera (update_thread)
        self._camera_processes: CameraProcesses | None = None
        self._camera_jobs: list[tuple[int, asyncio.Future]] = []
        self._first_t: int | None = None
        self._sources: Sequence[AsyncIterator] = ()

    # ---------------------------------------------------------------------------- samples
    def handle(self, sample: ImuSample | GpsFix | CameraFrame, arrived_ns: int | None = None) -> None:
        """Dispatch one sample (synchronous: called on the loop for every sample)."""
        for tap in self.sample_taps:
            try:
                tap(sample)
            except Exception as exc:  # a viewer's or recorder's failure must not cost the estimator a sample
                self.failures.record("sample tap", exc)
        if isinstance(sample, ImuSample):
            self._on_imu(sample, arrived_ns)
        elif isinstance(sample, ImuBatch):
            self._on_imu_batch(sample, arrived_ns)
        elif isinstance(sample, GpsFix):
            if self._gps_offset_ns:
                sample = replace(sample, t_ns=sample.t_ns + self._gps_offset_ns)
            self.status.saw("gps")
            self._add_measurement(sample.t_ns, lambda est, fix=sample: est.process_gps(fix), "gps")
        elif isinstance(sample, CameraFrame):
            self._on_camera(sample)
        else:
            self.status.count("unknown_sample_type")

    def _on_imu(self, sample: ImuSample, arrived_ns: int | None) -> None:
        entered = time.perf_counter_ns() if self.latency is not None else 0
        self.status.saw("imu")
        if self._first_t is None:
            self._first_t = sample.t_ns
        thread = self._fusion_thread
        busy = thread is not None and thread.busy  # the filter is the thread's: it hears of this sample later
        imu_range = self.options.imu_range
        if imu_range is not None and imu_range.exceeded(sample.gyro, sample.accel):
            if busy:
                thread.hold(lambda: self.est.count_refused_imu("out_of_range"))
            else:
                self.est.count_refused_imu("out_of_range")  # with the filter's, so reports show it beside non_finite
            return
        if busy:  # the pose from the detached prediction
            self._on_imu_while_fusing(thread, sample, entered, arrived_ns)
            return
        fusion = self.fusion
        if not fusion.add_imu(sample, fuse=False):
            return
        pose = fusion.output() if self.outputs else None
        if pose is not None:
            self._publish(pose, entered, arrived_ns)
        if thread is not None and fusion.heavy_due():  # milliseconds of work: not on the pose path
            thread.hand_over(fusion, self._fused_on_thread)
            return
        fusion.advance()  # the delayed filter's work, after the pose has left
        self._after_advance(pose is not None)

    def _publish(self, pose: OutputPose, entered: int, arrived_ns: int | None) -> None:
        """A pose to every output (each output's failure its own), into the history and its copy."""
        publishing = self.publishing
        for out in self.outputs:
            started = time.perf_counter_ns() if publishing is not None else 0
            try:
                out.publish(pose)
            except Exception as exc:  # a dead link degrades the service, never stops the others
                self.failures.record(f"output {out.name}", exc)
            if publishing is not None:
                publishing[out.name].add(time.perf_counter_ns() - started)
        self.poses_published += 1
        if self.latency is not None:
            left = time.perf_counter_ns()
            self.latency.add(left - (entered if arrived_ns is None else arrived_ns))
            self.handling.add(left - entered)
        self.last_pose = pose
        row = self.history.make_row(pose.p, pose.q, pose.v, pose.omega_b, pose.pose_cov)
        with self.history_lock:
            self.history.add_predicted(pose.t_ns, row)
        if self.history_feed is not None:
            self.history_feed.predicted(pose.t_ns, row)

    def _after_advance(self, published: bool) -> None:
        """After the delayed filter's work: what of the next pose is known already (its covariance), then a bounded
        slice of the fixed-lag smoother's."""
        if published:
            cov = self.fusion.next_pose_cov
            for out in self.outputs:
                prepare = getattr(out, "prepare", None)
                if prepare is not None:
                    try:
                        prepare(cov)
                    except Exception as exc:  # as publish: this output only
                        self.failures.record(f"output {out.name}", exc)
        if self.smoother is not None:
            try:
                smoothed = self.smoother.work()
                if smoothed:
                    self._on_smoothed(smoothed)
            except Exception as exc:  # the history keeps its filtered poses; the pose path is untouched
                self.failures.record("fixed-lag smoother (stopped)", exc)
                self.smoother = None

    def _on_imu_while_fusing(self, thread: FusionThread, sample: ImuSample, entered: int, arrived_ns: int | None) -> None:
        """A sample while a frame's update is on the fusion thread: its pose from the detached prediction now,
        the sample itself to the fusion core once the thread is done."""
        if not thread.hold(lambda: self.fusion.add_imu(sample, fuse=False)):
            self.status.count("imu_dropped_fusion_thread")
            return
        detached = thread.detached
        if detached is None or not self.outputs or not readings_finite(sample.gyro, sample.accel):
            return
        detached.step(sample.t_ns, sample.gyro, sample.accel)
        self._publish(detached.output(), entered, arrived_ns)

    def _fused_on_thread(self, fused: list[tuple[Callable[[Any], None], Any]], error: BaseException | None) -> None:
        """On the loop, once the thread's advance is done: its fused poses delivered, what was held given to the
        fusion core in order, and the filter's next advance (left to the next sample if it fuses another frame)."""
        for deliver, item in fused:
            deliver(item)
        if error is not None:
            self.failures.record("fusion thread", error)
        for action in self._fusion_thread.take_held():
            try:
                action()
            except Exception as exc:  # as handle(): counted, the rest goes on
                self.failures.record("handling held input", exc)
        if self.fusion.heavy_due():
            return  # the next sample hands it over (meanwhile the status, which waits for the thread, may go)
        self.fusion.advance()
        self._after_advance(bool(self.outputs))

    def _add_measurement(self, t_ns: int, apply: Apply, kind: str) -> None:
        """A measurement into the fusion queue; with a fusion thread, held while it works, and never fused on
        the spot (the next sample's advance takes it, and a frame's update then goes to the thread)."""
        thread = self._fusion_thread
        if thread is None:
            self.fusion.add_measurement(t_ns, apply, kind)
        elif thread.busy:
            if not thread.hold(lambda: self.fusion.add_measurement(t_ns, apply, kind, fuse_now=False)):
                self.status.count(f"{kind}_dropped_fusion_thread")
        else:
            self.fusion.add_measurement(t_ns, apply, kind, fuse_now=False)

    @property
    def fuses_runs(self) -> bool:
        """Whether IMU batches go to the fusion as runs: nobody wants the present pose (no outputs, probes
        or live smoother, as in an offline replay) and no tap sees the samples."""
        return not (self.outputs or self.sample_taps or self.latency is not None or self.smoother is not None)

    def _on_imu_batch(self, batch: ImuBatch, arrived_ns: int | None) -> None:
        """A replay's run of IMU samples: what :meth:`_on_imu` does for each, done once for all.

        Only where no present pose is wanted (no outputs, probes or live smoother, as in an offline
        replay) and no tap sees samples; otherwise each sample takes the live path, one by one.
        """
        if not self.fuses_runs:
            for sample in batch.samples():
                self.handle(sample, arrived_ns)
            return
        n = len(batch)
        if n == 0:
            return
        self.status.saw("imu", n)
        if self._first_t is None:
            self._first_t = int(batch.t_ns[0])
        t_ns, gyro, accel = batch.t_ns, batch.gyro, batch.accel
        out, finite = screened(gyro, accel, self.options.imu_range)  # one pass: range and finiteness
        if out.any():
            self.est.count_refused_imu("out_of_range", int(np.count_nonzero(out)))
            keep = ~out
            t_ns, gyro, accel, finite = t_ns[keep], gyro[keep], accel[keep], finite[keep]
        self.fusion.add_imu_batch(t_ns, gyro, accel, finite)

    # -------------------------------------------------------------------------- smoothing
    def finish_smoothing(self) -> None:
        """End of the data, after the fusion flush: the last segment closes, the rest is smoothed (once)."""
        if self._smoothing_finished or not self._records:
            return
        self._smoothing_finished = True
        self.est.finish_recording()
        if self.smoother is not None:
            smoothed = self.smoother.flush()
            if smoothed:
                self._on_smoothed(smoothed)

    def _on_smoothed(self, poses: list[SmoothedPose]) -> None:
        if self.keep_history:
            x = np.array([pose.x for pose in poses])
            rows = np.zeros((len(poses), ROW))
            rows[:, P], rows[:, Q], rows[:, V] = x[:, 0:3], x[:, 6:10], x[:, 3:6]
            rows[:, COV] = np.array([pose.pose_cov for pose in poses]).reshape(len(poses), 36)
            times = np.array([pose.t_ns for pose in poses], dtype=np.int64)
            with self.history_lock:
                self.history.add_smoothed(times, rows)
            if self.history_feed is not None:
                self.history_feed.smoothed(times, rows)
        if self.smoothed_hook is not None:
            self.smoothed_hook(poses)

    def _on_fused(self, pose: OutputPose) -> None:
        if self.keep_history:
            row = self.history.make_row(pose.p, pose.q, pose.v, pose.omega_b, pose.pose_cov)
            with self.history_lock:
                self.history.add_fused(pose.t_ns, row)
            if self.history_feed is not None:
                self.history_feed.fused(pose.t_ns, row)
        if self.trajectory is not None:
            try:
                self.trajectory.write(pose)
            except Exception as exc:  # a full disk must not stop the pose going out
                self.failures.record("trajectory file", exc)
        if self.fused_hook is not None:
            self.fused_hook(pose)

    def _on_fused_run(self, run: FusedRun) -> None:
        if self.fused_run_hook is None or self.keep_history or self.trajectory is not None:
            for pose in run.poses():
                self._on_fused(pose)
            return
        self.fused_run_hook(run)

    def _on_camera(self, frame: CameraFrame) -> None:
        if self._camera_offset_ns:
            frame = replace(frame, t_ns=frame.t_ns + self._camera_offset_ns)
        self.status.saw("camera")
        if self._camera_processes is not None:
            self._submit_to_process(frame)
            return
        if self.camera_processor is None or self._executor is None:
            self.status.count("camera_frames_unprocessed")
            return
        if len(self._camera_jobs) >= self.options.camera_workers and not self.options.lockstep:
            self.status.count("camera_frames_dropped_busy")
            return
        future = asyncio.get_running_loop().run_in_executor(self._executor, self.camera_processor, frame)
        future.add_done_callback(lambda f, t=frame.t_ns: self._camera_done(t, f))
        self._camera_jobs.append((frame.t_ns, future))

    def _submit_to_process(self, frame: CameraFrame) -> None:
        """The frame into an idle camera process's slot; its features come back as the threads' would."""
        processes = self._camera_processes
        if not processes.usable:  # its workers died too often: the camera is degraded, the rest runs on
            self.status.count("camera_frames_unprocessed")
            return
        image = frame.image
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.shape != processes.shape:
            # No slot fits it: rejected here, as the extraction would reject it (frame_quality's wrong_size).
            features = FrameFeatures.rejected(frame.t_ns, np.shape(image), "wrong_size")
            apply = self.camera_processor.fusing(frame, features)
            if apply is not None:
                self._add_measurement(frame.t_ns, apply, "camera")
            return
        job = processes.submit(image, frame.t_ns)
        if job is None:
            self.status.count("camera_frames_dropped_busy")
            return
        future = asyncio.wrap_future(job)
        future.add_done_callback(lambda f, fr=frame: self._camera_done(fr.t_ns, f, fr))
        self._camera_jobs.append((frame.t_ns, future))

    def _camera_done(self, t_ns: int, future: asyncio.Future, frame: CameraFrame | None = None) -> None:
        """On the loop, once a frame's work is finished: its measurement joins the fusion queue.

        ``frame``: the work was a camera process's, whose result is the frame's features."""
        self._camera_jobs = [(t, f) for t, f in self._camera_jobs if f is not future]
        if future.cancelled():
            return
        exc = future.exception()
        if exc is not None:
            self.status.count("camera_processing_errors")
            if not isinstance(exc, CameraWorkerDied):  # a death is reported by itself (on_death)
                log.error("feature extraction failed for the frame at t_ns=%d: %s", t_ns, exc)
            return
        apply = future.result() if frame is None else self.camera_processor.fusing(frame, future.result())
        if apply is not None:
            self._add_measurement(t_ns, apply, "camera")

    async def _camera_process_idle(self) -> None:
        """Lock-step: a frame waits for an idle camera process (never dropped), so a replay gives the same result."""
        processes = self._camera_processes
        while processes.usable and not processes.idle:
            if self._camera_jobs:
                await asyncio.wait([f for _, f in self._camera_jobs], return_when=asyncio.FIRST_COMPLETED)
            else:  # a worker is being started again
                await asyncio.sleep(0.01)
            await asyncio.sleep(0)  # their done-callbacks queue the measurements

    async def _before_imu(self, t_ns: int) -> None:
        """Lock-step: frames the horizon is about to pass must have their features queued first."""
        due = t_ns - self.fusion.delay_ns
        while waiting := [f for t, f in self._camera_jobs if t <= due]:
            await asyncio.wait(waiting)
            await asyncio.sleep(0)  # their done-callbacks queue the measurements

    # ------------------------------------------------------------------------------- loop
    async def _consume(self, source: AsyncIterator, name: str) -> None:
        """Feed one source's samples; a source that fails is reported and ends, the others go on.

        A sample whose handling raises is counted (``handling <kind>``) and skipped: the filter's
        health check (estimator.health) catches a state such a failure left unsound.
        """
        lockstep = self.options.lockstep
        try:
            async for sample in source:
                if lockstep and self._camera_jobs and isinstance(sample, (ImuSample, ImuBatch)):
                    await self._before_imu(sample.t_ns if isinstance(sample, ImuSample) else int(sample.t_ns[-1]))
                elif lockstep and self._camera_processes is not None and isinstance(sample, CameraFrame):
                    await self._camera_process_idle()
                try:
                    self.handle(sample, getattr(source, "last_arrival_ns", None) if self.latency is not None else None)
                except Exception as exc:
                    self.failures.record(f"handling {type(sample).__name__}", exc)
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # a dead sensor degrades the estimate and is reported
            self.failures.record(f"source {name}", exc)

    def status_document(self) -> dict[str, Any]:
        links = {o.name: o.link_stats() if hasattr(o, "link_stats") else getattr(o, "stats", {}) for o in self.outputs}
        with self.history_lock:
            bounds = self.history.bounds()
            held = len(self.history)
        dropped = {getattr(src, "name", str(i)): src.dropped for i, src in enumerate(self._sources) if getattr(src, "dropped", 0)}
        extra = {
            "t_ns": self.last_pose.t_ns if self.last_pose is not None else None,
            "source_overflows": dropped,  # samples a device thread had to drop because the loop fell behind
            "history": {"poses": held, "from_t_ns": bounds[0] if bounds else None, "to_t_ns": bounds[1] if bounds else None},
            "outputs": links,
            "quality": pose_quality(self.last_pose) if self.last_pose is not None else 0,
            "pose_problem": pose_problem(self.last_pose) if self.last_pose is not None else "no pose yet",
            **self._imu_missing(),
            **({"camera_process": self._camera_processes.report()} if self._camera_processes is not None else {}),
            **({"fusion_thread": self._fusion_thread.report()} if self._fusion_thread is not None else {}),
            "failures": self.failures.report(),  # isolated failures of outputs, sources, the trajectory file
        }
        # Input links with their own counters (the GPS over MAVLink on a link of its own), beside the outputs'.
        inputs = {getattr(src, "name", str(i)): src.driver.link_stats() for i, src in enumerate(self._sources)
                  if hasattr(getattr(src, "driver", None), "link_stats")}
        if inputs:
            extra["inputs"] = inputs
        if self.recorder is not None:  # a live run's flight recording (its own status, never an error here)
            extra["recording"] = {"status": self.recorder.status, "rows": dict(self.recorder.rows)}
        return self.status.snapshot(self.est, self.fusion, extra)

    def _imu_missing(self) -> dict[str, Any]:
        """The last pose is no longer one to use when the IMU has gone quiet: the filter holds its state over the
        hole (it said so at the last measurement), or no sample has arrived for ``imu_gap_reset_s`` (host clock)."""
        limit_s = self.est.options.health.imu_gap_reset_s
        imu = self.status.sensors.get("imu")
        age_s = None if imu is None or imu.last_arrival is None else self.status.clock() - imu.last_arrival
        if self.est.health.imu_missing_since_ns is None and (age_s is None or age_s <= limit_s):
            return {}
        return {"quality": 0, "pose_problem": "IMU missing: the state is held, not flown"}

    async def _status_loop(self, stop: asyncio.Event) -> None:
        period = self.options.status_period_s
        while not stop.is_set():
            await stopped_within(stop, period)  # then one last status on the way out
            if self._fusion_thread is not None:
                await self._fusion_thread.idle()  # the status reads the filter: not while the thread changes it
            try:
                doc = self.status_document()
            except Exception as exc:  # the status is a report: a bug in it must not stop the run
                self.failures.record("status document", exc)
                continue
            for out in self.outputs:
                try:
                    out.publish_status(doc)
                except Exception as exc:  # one output's failure must not silence the others
                    self.failures.record(f"output {out.name} status", exc)
            if self.trajectory is not None:
                try:
                    self.trajectory.flush()
                except Exception as exc:
                    self.failures.record("trajectory file", exc)

    @staticmethod
    async def _wait(feeders: set[asyncio.Task], waiter: asyncio.Task, duration_s: float | None) -> str:
        """Why the run ends: a stop request, the duration, or every source exhausted (a failed one raises)."""
        deadline = None if duration_s is None else time.perf_counter() + duration_s
        while feeders:
            timeout = None if deadline is None else max(deadline - time.perf_counter(), 0.0)
            done, _ = await asyncio.wait(feeders | {waiter}, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
            if waiter in done:
                return "signal"
            if not done:
                return "duration"
            for task in done:
                feeders.discard(task)
                task.result()
        return "end of data"

    async def run(self, sources: Sequence[AsyncIterator], stop: asyncio.Event | None = None,
                  duration_s: float | None = None) -> RunSummary:
        """Run until ``stop`` is set, every source is exhausted, or ``duration_s`` (wall) has passed."""
        stop = stop or asyncio.Event()
        wall0 = time.perf_counter()
        self._sources = sources
        # Camera work runs at normal scheduling, niced, even when the loop (and the threads it starts) is real-time.
        in_process = self.options.camera_process and self.camera_processor is not None
        if not in_process:
            self._executor = ThreadPoolExecutor(max_workers=self.options.camera_workers, thread_name_prefix="camera",
                                                initializer=background_thread_priority)
        # Paced (live) runs: OpenCV's own worker pool would run feature extraction on every core at
        # normal priority beside the loop; one thread per camera worker keeps it in the niced workers
        # (SIFT ~40 % slower per frame, well inside a frame period). Full-speed replays with several
        # workers (two per core) extract whole frames in parallel, each on one thread; with one
        # worker they keep the pool. Without a camera OpenCV is not even loaded.
        opencv_threads = None
        if self.camera_processor is not None and not in_process:
            import cv2

            opencv_threads = cv2.getNumThreads()
            if not self.options.lockstep or self.options.camera_workers > 1:
                cv2.setNumThreads(1)
        opened: list[PoseOutput] = []
        # Without outputs nobody reads the present pose (an offline replay): no output predictor,
        # and no history of poses for queries nobody can ask.
        self.fusion.predict = self.keep_history = bool(self.outputs)
        frame_hook = None  # the frame processor's on_frame, while the fusion thread's updates call it
        if (self.options.update_thread and self.outputs and self.camera_processor is not None
                and not self.options.lockstep):
            self._fusion_thread = FusionThread()
            self._fusion_thread.open()
            frame_hook = getattr(self.camera_processor, "on_frame", None)
            if frame_hook is not None:  # viewers and recorders (an MCAP file) are written from the loop only
                loop = asyncio.get_running_loop()
                self.camera_processor.on_frame = lambda *frame: loop.call_soon_threadsafe(frame_hook, *frame)
        try:
            for out in self.outputs:
                try:
                    out.open()
                except Exception as exc:  # zenoh.ZError, serial and socket errors: say which output
                    raise OSError(f"the {out.name} output could not open: {exc}") from exc
                opened.append(out)
            if in_process:
                loop = asyncio.get_running_loop()
                self._camera_processes = await asyncio.to_thread(
                    self._start_camera_processes,
                    lambda exc: loop.call_soon_threadsafe(self.failures.record, "camera process", exc))
            # Everything built so far lives for the whole run: keep it out of the cyclic collector's
            # full passes, whose pauses would otherwise land on the pose path. Only the young
            # generations are collected first: a full pass over the imported libraries' objects
            # (numba's alone are ~100 000) costs ~60 ms, a fifth of a two-minute replay; what old
            # garbage it would have found is freed after the run, when the objects are unfrozen.
            gc.collect(1)
            gc.freeze()
            if self.options.realtime_priority is not None:
                set_thread_priority(self.options.realtime_priority)
            background = [asyncio.create_task(o.serve(stop), name=f"serve-{o.name}") for o in self.outputs]
            background.append(asyncio.create_task(self._status_loop(stop), name="status"))
            feeders = [asyncio.create_task(self._consume(s, getattr(s, "name", str(i))), name=f"source-{i}")
                       for i, s in enumerate(sources)]
            waiter = asyncio.create_task(stop.wait())
            stopped_by = await self._wait(set(feeders), waiter, duration_s)
            stop.set()
            for task in feeders:
                task.cancel()
            await asyncio.gather(*feeders, return_exceptions=True)
            if self._camera_jobs:
                await asyncio.wait([f for _, f in self._camera_jobs], timeout=10.0)
                await asyncio.sleep(0)  # their done-callbacks queue the measurements
            if self._fusion_thread is not None:
                await self._fusion_thread.idle()  # the filter back on the loop, what it held given to it
            self.fusion.flush()
            self.finish_smoothing()
            for task, result in zip(background, await asyncio.gather(*background, return_exceptions=True)):
                if isinstance(result, Exception):
                    log.error("%s stopped with an error: %r", task.get_name(), result)
            waiter.cancel()
        finally:
            stop.set()
            for out in reversed(opened):
                try:
                    out.close()
                except Exception as exc:  # closing one link must not keep the others open
                    log.error("closing %s: %s", type(out).__name__, exc)
                    if hasattr(out, "incomplete"):  # a file output that could not be finished
                        self._close_errors[out.name] = f"{getattr(exc, 'strerror', None) or exc}"
            if self._executor is not None:
                self._executor.shutdown(wait=True, cancel_futures=True)
            if self._fusion_thread is not None:
                self._fusion_thread.close()
                if frame_hook is not None:
                    self.camera_processor.on_frame = frame_hook
            if self._camera_processes is not None:
                self._camera_processes.close()  # the ring unlinked; its report stays for the summary
            if opencv_threads is not None:
                import cv2

                cv2.setNumThreads(opencv_threads)
            gc.unfreeze()
            if self.options.realtime_priority is not None:
                set_thread_priority(None)
            if self.trajectory is not None:
                self.trajectory.close()
        newest = self.fusion.newest_imu_t_ns
        p50, p99, pmax = self.latency.percentiles_ms(50, 99, 100) if self.latency is not None else (float("nan"),) * 3
        return RunSummary(
            imu_samples=self.status.sensors["imu"].total if "imu" in self.status.sensors else 0,
            poses_published=self.poses_published,
            trajectory_lines=self.trajectory.lines if self.trajectory is not None else 0,
            wall_s=time.perf_counter() - wall0,
            data_s=(newest - self._first_t) * 1e-9 if newest is not None and self._first_t is not None else 0.0,
            stopped_by=stopped_by,
            latency_ms={"p50": p50, "p99": p99, "max": pmax},
            status=self.status_document(),
            trajectory_error=self.trajectory.error if self.trajectory is not None else None,
            incomplete=self.incomplete_outputs(),
        )

    @property
    def camera_processes(self) -> CameraProcesses | None:
        """The camera's worker processes while a run with ``camera_process`` goes on (their pids, their report)."""
        return self._camera_processes

    def _start_camera_processes(self, on_death: Callable[[CameraWorkerDied], None]) -> CameraProcesses:
        """``camera_workers`` extraction processes for the processor's frames (its ``options``, ``expected_shape``
        and ``fusing``: a FrameProcessor's), started and ready."""
        processor = self.camera_processor
        shape = getattr(processor, "expected_shape", None)
        if shape is None or not hasattr(processor, "fusing"):
            raise ValueError("camera processes need a frame processor that knows the camera's frame shape "
                             "(expected_shape) and fuses features extracted elsewhere (fusing)")
        processes = CameraProcesses(processor.options, shape, shape, self.options.camera_workers, on_death)
        try:
            processes.start()
        except BaseException:
            processes.close()
            raise
        return processes

    def incomplete_outputs(self) -> list[str]:
        """Each requested file output (the trajectory file, an MCAP recording) that could not be written in full,
        with the reason: the run then did not do what was asked, whatever the poses did."""
        out = []
        if self.trajectory is not None and self.trajectory.error:
            out.append(f"the trajectory file {self.trajectory.path} is incomplete: {self.trajectory.error}")
        for output in self.outputs:
            why = self._close_errors.get(output.name) or getattr(output, "incomplete", None)
            if why:
                out.append(f"the {output.name} output {getattr(output, 'path', '')} is incomplete: {why}".replace("  ", " "))
        return out
