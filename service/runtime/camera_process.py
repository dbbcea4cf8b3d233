"""Feature extraction in processes of their own, so that SIFT never holds the interpreter the IMU path needs.

Each worker process owns one slot of a shared-memory ring sized from the camera's frame shape; a
frame is copied into an idle worker's slot and its time sent over a pipe, and the worker returns
the frame's features (keypoints, descriptors) over another. One frame at most per worker is in
flight: :meth:`CameraProcesses.submit` answers None when every worker is busy, and the runtime
drops and counts that frame, as it does when its camera threads are busy. The extraction is the
threads' own (:class:`~vtolpose.estimator.FrameExtractor`), on one OpenCV thread as theirs, so
the features are the same.

The workers are started with 'spawn' (never forked from a process with threads). A worker that
dies fails its frame, is reported and started again, up to :data:`MAX_RESTARTS` times in all;
after that the camera is degraded and frames go unprocessed, the service runs on. :meth:`close`
stops the workers and unlinks the ring.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import threading
from concurrent.futures import Future
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from multiprocessing.shared_memory import SharedMemory
from typing import Any, Callable

import numpy as np

from vtolpose.estimator import FeatureOptions, FrameFeatures

log = logging.getLogger(__name__)

CAMERA_NICE = 10  # camera workers, threads or processes: feature extraction yields a contended core to the pose path
MAX_RESTARTS = 5  # workers started again after dying, in all; then the camera is given up
READY_TIMEOUT_S = 60.0  # a worker imports numpy and OpenCV before it answers


class CameraWorkerDied(RuntimeError):
    """A camera worker process ended with a frame in hand."""


def _background_priority() -> None:
    """Normal scheduling (never the loop's SCHED_FIFO), niced: the pose path wins a contended core."""
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        os.setpriority(os.PRIO_PROCESS, 0, CAMERA_NICE)
    except (AttributeError, OSError) as exc:
        log.debug("camera process priority not set: %s", exc)


def _work(jobs: Connection, results: Connection, ring_name: str, slot: int, shape: tuple[int, int],
          options: FeatureOptions, expected_shape: tuple[int, int] | None) -> None:
    """A worker process: extract each frame put in its slot until told to stop (None) or the pipe closes."""
    import cv2

    from vtolpose.estimator import FrameExtractor
    from vtolpose.service.runtime.threads import limit_blas_threads

    _background_priority()
    cv2.setNumThreads(1)  # as the camera threads: whole frames in parallel, each on one thread
    limit_blas_threads(1)
    ring = SharedMemory(name=ring_name)
    try:
        image = np.ndarray(shape, np.uint8, ring.buf, offset=slot * shape[0] * shape[1])
        extractor = FrameExtractor(options, expected_shape)
        results.send("ready")
        while True:
            try:
                t_ns = jobs.recv()
            except EOFError:
                break
            if t_ns is None:
                break
            try:  # the tracker keeps the last image: a copy, the slot is reused
                features: Any = extractor(image.copy() if extractor.in_order else image, t_ns)
            except Exception as exc:  # this frame fails; the worker goes on
                features = exc
            results.send(features)
        del image
    finally:
        ring.close()


@dataclass
class _Worker:
    slot: int
    process: Any = None
    jobs: Connection | None = None
    results: Connection | None = None
    job: Future | None = None  # the frame in hand
    ready: bool = False


@dataclass
class CameraProcessStats:
    started: int = 0
    restarts: int = 0
    deaths: int = 0
    frames: int = 0
    last_death: str | None = None


class CameraProcesses:
    """``workers`` extraction processes, one shared-memory slot each, for frames of ``shape`` (grey, uint8)."""

    def __init__(self, options: FeatureOptions, expected_shape: tuple[int, int] | None, shape: tuple[int, int],
                 workers: int = 1, on_death: Callable[[CameraWorkerDied], None] | None = None) -> None:
        """``on_death``: told of each worker's death, on the reader thread (the runtime reports it in health)."""
        if workers < 1:
            raise ValueError(f"camera processes: at least one worker, got {workers}")
        self.options, self.expected_shape = options, expected_shape
        self.shape = (int(shape[0]), int(shape[1]))
        self._context = multiprocessing.get_context("spawn")
        self._ring = SharedMemory(create=True, size=workers * self.shape[0] * self.shape[1])
        self.ring_name = self._ring.name
        self._slots = np.ndarray((workers, *self.shape), np.uint8, self._ring.buf)
        self._workers = [_Worker(k) for k in range(workers)]
        self._lock = threading.Lock()
        self._reader: threading.Thread | None = None
        self._wake_r, self._wake_w = multiprocessing.Pipe(duplex=False)  # tells the reader to look again or stop
        self._closing = False
        self.given_up = False
        self.on_death = on_death
        self.stats = CameraProcessStats()

    # ----------------------------------------------------------------------------- the loop's side
    def start(self) -> None:
        """Start every worker and wait until each has loaded OpenCV; then the reader thread takes their answers."""
        for worker in self._workers:
            self._spawn(worker)
        for worker in self._workers:
            self._await_ready(worker)
        self._reader = threading.Thread(target=self._read, name="camera-process-reader", daemon=True)
        self._reader.start()

    @property
    def usable(self) -> bool:
        """False once the workers have died more often than :data:`MAX_RESTARTS`: the camera is given up."""
        return not self.given_up

    @property
    def idle(self) -> bool:
        with self._lock:
            return any(w.ready and w.job is None for w in self._workers)

    def submit(self, image: np.ndarray, t_ns: int) -> Future | None:
        """The future features of the frame, or None when every worker has a frame in hand (or is restarting).

        ``image`` must be grey uint8 of :attr:`shape`; anything else is the caller's to reject."""
        with self._lock:
            worker = next((w for w in self._workers if w.ready and w.job is None), None)
            if worker is None:
                return None
            worker.job = job = Future()
            job.set_running_or_notify_cancel()
        self._slots[worker.slot] = image
        try:
            worker.jobs.send(int(t_ns))
        except OSError as exc:  # the worker is gone: the reader thread is about to see it too
            with self._lock:
                worker.job = None
            job.set_exception(CameraWorkerDied(f"camera worker {worker.slot} is gone ({exc})"))
        self.stats.frames += 1
        return job

    def report(self) -> dict[str, Any]:
        """For the status document: how the workers are, and what befell them."""
        with self._lock:
            alive = sum(w.process is not None and w.process.is_alive() for w in self._workers)
        return {"workers": len(self._workers), "alive": alive, "restarts": self.stats.restarts,
                "deaths": self.stats.deaths, "last_death": self.stats.last_death, "frames": self.stats.frames,
                "given_up": self.given_up}

    def pids(self) -> list[int]:
        with self._lock:
            return [w.process.pid for w in self._workers if w.process is not None]

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the workers (a frame in hand is finished first, within ``timeout_s``), then unlink the ring."""
        self._closing = True
        self._wake_w.send(None)
        if self._reader is not None:
            self._reader.join(timeout_s)
        for worker in self._workers:
            self._stop(worker, timeout_s)
        self._wake_r.close()
        self._wake_w.close()
        del self._slots
        self._ring.close()
        self._ring.unlink()

    # ---------------------------------------------------------------------------- worker lifetimes
    def _spawn(self, worker: _Worker) -> None:
        jobs_r, jobs_w = self._context.Pipe(duplex=False)
        results_r, results_w = self._context.Pipe(duplex=False)
        process = self._context.Process(
            target=_work, args=(jobs_r, results_w, self.ring_name, worker.slot, self.shape, self.options,
                                self.expected_shape),
            name=f"vtolpose-camera-{worker.slot}", daemon=True)
        process.start()
        jobs_r.close()  # the child's ends: closed here, so that its death reads as the end of the pipe
        results_w.close()
        worker.process, worker.jobs, worker.results, worker.ready = process, jobs_w, results_r, False
        self.stats.started += 1

    def _await_ready(self, worker: _Worker) -> bool:
        try:
            if worker.results.poll(READY_TIMEOUT_S) and worker.results.recv() == "ready":
                with self._lock:
                    worker.ready = True
                return True
        except (EOFError, OSError) as exc:  # the worker died before it answered: its pipe is closed
            log.error("camera worker %d did not start: %s", worker.slot, exc or type(exc).__name__)
            return False
        log.error("camera worker %d did not start", worker.slot)
        return False

    def _stop(self, worker: _Worker, timeout_s: float) -> None:
        process = worker.process
        if process is None:
            return
        try:
            worker.jobs.send(None)
        except OSError as exc:  # already gone (its pipe closed): the join below finds it ended
            log.debug("camera worker %d: stop not sent: %s", worker.slot, exc)
        process.join(timeout_s)
        if process.is_alive():
            process.kill()
            process.join()
        for conn in (worker.jobs, worker.results):
            conn.close()
        with self._lock:
            worker.process, worker.ready = None, False
        job = worker.job
        if job is not None and not job.done():
            job.set_exception(CameraWorkerDied(f"camera worker {worker.slot} stopped with a frame in hand"))
        worker.job = None

    # ------------------------------------------------------------------------------ reader thread
    def _read(self) -> None:
        """Take each worker's answers; a worker that died fails its frame and is started again (a bounded number of times)."""
        while not self._closing:
            with self._lock:
                by_conn = {w.results: w for w in self._workers if w.process is not None}
            ready = wait([self._wake_r, *by_conn])
            for conn in ready:
                if conn is self._wake_r:
                    conn.recv()
                    continue
                worker = by_conn[conn]
                try:
                    answer = conn.recv()
                except (EOFError, OSError):
                    if not self._closing:
                        self._died(worker)
                    continue
                if answer == "ready":
                    with self._lock:
                        worker.ready = True
                    continue
                with self._lock:
                    job, worker.job = worker.job, None
                if job is None:
                    continue
                if isinstance(answer, FrameFeatures):
                    job.set_result(answer)
                else:
                    job.set_exception(answer if isinstance(answer, BaseException) else RuntimeError(repr(answer)))

    def _died(self, worker: _Worker) -> None:
        worker.process.join(1.0)  # reaped: its exit code is known
        self.stats.deaths += 1
        why = f"camera worker {worker.slot} (pid {worker.process.pid}) died, exit code {worker.process.exitcode}"
        self.stats.last_death = why
        for conn in (worker.jobs, worker.results):
            conn.close()
        with self._lock:
            job, worker.job, worker.process, worker.ready = worker.job, None, None, False
        if job is not None:
            job.set_exception(CameraWorkerDied(why))
        if self.on_death is not None:
            try:
                self.on_death(CameraWorkerDied(why))
            except Exception as exc:  # a closed loop at shutdown: the death is in the stats all the same
                log.debug("camera worker death not reported: %s", exc)
        if self.stats.restarts < MAX_RESTARTS:
            log.error("%s; starting it again", why)
            self.stats.restarts += 1
            try:
                self._spawn(worker)  # its "ready" arrives through this loop
                return
            except OSError as exc:  # no process to be had (memory, process limits)
                log.error("camera worker %d could not be started again: %s", worker.slot, exc)
        else:
            log.error("%s; restarted %d times already: not again", why, self.stats.restarts)
        with self._lock:
            self.given_up = not any(w.process is not None for w in self._workers)
