"""Sample sources for the runtime: async iterators of typed samples (ImuSample, GpsFix, CameraFrame).

Live devices have blocking drivers (``open()``, ``read(timeout_s) -> readings``, ``close()``);
:class:`ThreadedSource` reads one on its own thread and hands each sample to the event loop,
so a slow device never blocks the loop. :class:`ReplaySource` plays a dataset's streams in
time order, paced by a :class:`ReplayClock`; the runtime cannot tell the two apart.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import deque
from typing import Any, AsyncIterator, Callable, Iterator, Sequence, Union

import numpy as np

from vtolpose.drivers.files.dataset import Dataset
from vtolpose.estimator import CameraFrame, GpsFix, ImuBatch, ImuSample

log = logging.getLogger(__name__)

Sample = Union[ImuSample, ImuBatch, GpsFix, CameraFrame]


class ReplayClock:
    """Maps dataset time to wall time at ``speed`` × real time; speed 0 means no waiting at all."""

    YIELD_EVERY = 256  # at full speed, let other tasks (status, links, queries) run this often

    def __init__(self, speed: float) -> None:
        if not speed >= 0.0:
            raise ValueError(f"replay speed must be >= 0 (0 = as fast as possible), got {speed}")
        self.speed = speed
        self._origin: tuple[int, float] | None = None
        self._n = 0

    def now_ns(self) -> int | None:
        """Dataset time now (paced replays, once started); None as fast as possible or before the first sample."""
        if self.speed == 0.0 or self._origin is None:
            return None
        t0, wall0 = self._origin
        return t0 + int((time.perf_counter() - wall0) * self.speed * 1e9)

    async def wait_until(self, t_ns: int, samples: int = 1) -> None:
        """Wait for ``t_ns``; ``samples``: how many samples are handed out at it (a batch counts each)."""
        n = self._n
        self._n = n + samples
        if self.speed == 0.0:
            if self._n // self.YIELD_EVERY != n // self.YIELD_EVERY:
                await asyncio.sleep(0)
            return
        now = time.perf_counter()
        if self._origin is None:
            self._origin = (t_ns, now)
        t0, wall0 = self._origin
        delay = wall0 + (t_ns - t0) * 1e-9 / self.speed - now
        if delay > 0:
            await asyncio.sleep(delay)
        elif self._n // self.YIELD_EVERY != n // self.YIELD_EVERY:
            await asyncio.sleep(0)


def merged_order(*times: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(stream number, index) of every sample in time order; at equal times the lower stream number goes first."""
    streams = [(k, np.asarray(t, dtype=np.int64)) for k, t in enumerate(times) if t is not None and len(t)]
    all_t = np.concatenate([t for _, t in streams])
    kinds = np.concatenate([np.full(len(t), k, np.int8) for k, t in streams])
    index = np.concatenate([np.arange(len(t)) for _, t in streams])
    order = np.lexsort((kinds, all_t))
    return kinds[order], index[order]


PROGRESS_EVERY = 100  # IMU samples between progress calls (0.5 s of data at 200 Hz)
# As fast as possible, each frame is handed over this much data time before its own, so that its features
# are being extracted on the other cores while the IMU's work goes on; waiting only at the fusion horizon
# (0.15 s of data, a few tens of milliseconds at full speed), the loop would mostly wait for them. The
# frame keeps its own time and is fused at it, so the result is the same.
FRAME_LEAD_S = 1.0


class ReplaySource:
    """A dataset's IMU, GPS and (optionally) camera streams in time order, paced by ``clock``.

    At equal times the IMU goes first, then GPS, then camera (the offline replay's order).
    Camera frames are given as ``(t_ns, path)`` with a ``load(path) -> image | None``; the next
    frame is loaded on a thread ahead of its time, so that decoding never delays the IMU when paced
    and, as fast as possible, runs beside the IMU's work instead of between it.
    As fast as possible, frames are handed over :data:`FRAME_LEAD_S` of data early (not when paced).
    ``last_arrival_ns`` is the ``perf_counter_ns`` at which the latest sample was handed out.
    """

    def __init__(
        self,
        dataset: Dataset,
        sensors: Sequence[str],
        clock: ReplayClock,
        stop_after_s: float | None = None,
        frames: Sequence[tuple[int, Any]] | None = None,
        load: Callable[[Any], np.ndarray | None] | None = None,
        on_progress: Callable[[float], None] | None = None,
        start_after_s: float | None = None,
    ) -> None:
        self.imu = dataset.imu()
        self.gps = dataset.gps() if "gps" in sensors else None
        if len(self.imu.t_ns) == 0:
            raise ValueError(f"{dataset.root}: the IMU stream has no valid samples")
        if frames and load is None:
            raise ValueError("camera frames need a load(path) function")
        self.frames = list(frames or [])
        self.load = load
        self.clock = clock
        self.stop_after_ns = None if stop_after_s is None else int(stop_after_s * 1e9)
        # Joining the recording later (a service restarted in flight): nothing before this is played.
        self.start_after_ns = 0 if start_after_s is None else int(round(start_after_s * 1e9))
        if self.start_after_ns < 0 or int(self.imu.t_ns[0]) + self.start_after_ns > int(self.imu.t_ns[-1]):
            raise ValueError(f"{dataset.root}: start {start_after_s} s is outside the recording "
                             f"(0 to {(int(self.imu.t_ns[-1]) - int(self.imu.t_ns[0])) * 1e-9:.3f} s of IMU data)")
        self.last_arrival_ns: int | None = None
        self.unreadable_frames = 0
        self.duration_s = (int(self.imu.t_ns[-1]) - int(self.imu.t_ns[0])) * 1e-9
        self.on_progress = on_progress  # seconds of data handed out, every PROGRESS_EVERY IMU samples

    async def _frame(self, k: int, ahead: dict[int, asyncio.Future]) -> CameraFrame | None:
        t_ns, path = self.frames[k]
        loop = asyncio.get_running_loop()
        future = ahead.pop(k, None) or loop.run_in_executor(None, self.load, path)
        if k + 1 < len(self.frames):
            ahead[k + 1] = loop.run_in_executor(None, self.load, self.frames[k + 1][1])
        image = await future
        if image is None:
            self.unreadable_frames += 1
            return None
        return CameraFrame(t_ns, image, k)

    async def __aiter__(self) -> AsyncIterator[Sample]:
        imu, gps = self.imu, self.gps
        batches = self.clock.speed == 0.0
        frame_t = np.array([t for t, _ in self.frames], dtype=np.int64) if self.frames else None
        if frame_t is not None and batches:
            frame_t = frame_t - int(FRAME_LEAD_S * 1e9)
        kinds, indices = merged_order(imu.t_ns, gps.t_ns if gps is not None else np.zeros(0, np.int64), frame_t)
        imu_t = imu.t_ns
        t_first = int(imu_t[0])
        t_end = t_first + self.stop_after_ns if self.stop_after_ns is not None else None
        t_start = t_first + self.start_after_ns
        ahead: dict[int, asyncio.Future] = {}
        progress = self.on_progress
        # As fast as possible, each run of IMU samples between two other samples goes out as one
        # ImuBatch (at most YIELD_EVERY long): the same samples in the same order, handed over once.
        for kind, i, count in _segments(kinds, indices, ReplayClock.YIELD_EVERY if batches else 1):
            if batches and kind == 0:
                i_end = i + count
                if imu_t[i] < t_start:  # a replay told to start later: skip what comes before
                    i += int(np.searchsorted(imu_t[i:i_end], t_start, side="left"))
                stop = i_end if t_end is None else i + int(np.searchsorted(imu_t[i:i_end], t_end, side="right"))
                if stop > i:
                    t_last = int(imu_t[stop - 1])
                    if progress is not None and (i + PROGRESS_EVERY - 1) // PROGRESS_EVERY * PROGRESS_EVERY < stop:
                        progress((t_last - t_first) * 1e-9)
                    await self.clock.wait_until(t_last, stop - i)
                    self.last_arrival_ns = time.perf_counter_ns()
                    yield ImuBatch(imu_t[i:stop], imu.gyro[i:stop], imu.accel[i:stop])
                if stop < i_end:
                    return  # past stop_after_s
                continue
            if kind == 0:
                t = int(imu_t[i])
            elif kind == 1:
                t = int(gps.t_ns[i])
            else:
                t = self.frames[i][0]
            if t < t_start:
                continue
            if kind == 0:
                sample: Sample | None = ImuSample(t, imu.gyro[i], imu.accel[i])
                if progress is not None and i % PROGRESS_EVERY == 0:
                    progress((t - t_first) * 1e-9)
            elif kind == 1:
                sample = GpsFix(t, gps.p_ned[i], float(gps.sigma_h[i]), float(gps.sigma_v[i]))
            if t_end is not None and t > t_end:
                if kind == 2 and batches:
                    continue  # a frame handed over early: the other streams go on up to the end
                return
            await self.clock.wait_until(t)
            if kind == 2:
                sample = await self._frame(i, ahead)
                if sample is None:
                    continue
            self.last_arrival_ns = time.perf_counter_ns()
            yield sample


def _segments(kinds: np.ndarray, indices: np.ndarray, longest: int) -> Iterator[tuple[int, int, int]]:
    """A merged order as (stream, first index, count): runs of IMU samples (stream 0, consecutive indices)
    of at most ``longest``, every other sample alone. Nothing is made per sample (an hour at 200 Hz is
    720,000 of them): the runs are found from where the other streams' samples sit."""
    n = len(kinds)
    previous = 0
    for position in [*np.flatnonzero(kinds != 0).tolist(), n]:
        if position > previous:  # IMU samples from previous to position
            first, count = int(indices[previous]), position - previous
            for offset in range(0, count, longest):
                yield 0, first + offset, min(longest, count - offset)
        if position < n:
            yield int(kinds[position]), int(indices[position]), 1
        previous = position + 1


class ThreadedSource:
    """A blocking driver read on a dedicated thread, exposed as an async iterator of samples.

    ``convert`` turns one driver reading into a sample (or None to skip it); ``tap`` sees every
    raw reading on the reader thread (e.g. a flight recorder). If the loop falls behind by
    ``max_queue`` samples, the oldest are dropped and counted rather than growing without bound.
    """

    def __init__(
        self,
        name: str,
        driver: Any,
        convert: Callable[[Any], Sample | None],
        read_timeout_s: float = 0.1,
        tap: Callable[[Any], None] | None = None,
        max_queue: int = 2000,
    ) -> None:
        self.name = name
        self.driver = driver
        self.convert = convert
        self.read_timeout_s = read_timeout_s
        self.tap = tap
        self.dropped = 0
        self.last_arrival_ns: int | None = None
        self._queue: deque[tuple[Sample, int]] = deque(maxlen=max_queue)
        self._wake: asyncio.Event | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _read_loop(self, loop: asyncio.AbstractEventLoop) -> None:
        try:
            while not self._stop.is_set():
                started = time.monotonic()
                readings = self.driver.read(self.read_timeout_s)
                if not readings:
                    if getattr(self.driver, "ended", False):  # a file source at its end
                        return
                    if time.monotonic() - started < 1e-3:  # a driver that does not block: do not spin
                        time.sleep(min(self.read_timeout_s, 0.01))
                    continue
                if not isinstance(readings, list):
                    readings = [readings]
                for reading in readings:
                    if self.tap is not None:
                        self.tap(reading)
                    sample = self.convert(reading)
                    if sample is None:
                        continue
                    if len(self._queue) == self._queue.maxlen:
                        self.dropped += 1
                    self._queue.append((sample, time.perf_counter_ns()))
                loop.call_soon_threadsafe(self._wake.set)
        except Exception:  # a driver bug must not kill the process silently
            log.exception("%s: reader thread stopped", self.name)
        finally:
            self.driver.close()
            try:
                loop.call_soon_threadsafe(self._wake.set)
            except RuntimeError:  # the loop is already closed: nobody is waiting
                log.debug("%s: reader ended after the loop closed", self.name)

    async def __aiter__(self) -> AsyncIterator[Sample]:
        loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        self._thread = threading.Thread(target=self._read_loop, args=(loop,), name=f"source-{self.name}", daemon=True)
        self._thread.start()
        try:
            while True:
                while self._queue:
                    sample, self.last_arrival_ns = self._queue.popleft()
                    yield sample
                if not self._thread.is_alive():
                    if self._queue:  # appended just before the thread ended
                        continue
                    return
                self._wake.clear()
                if not self._queue:
                    await self._wake.wait()
        finally:
            self.close()

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the reader thread; the driver is closed on it (ports released)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
