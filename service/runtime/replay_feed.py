"""A recorded or simulated dataset fed through the onboard runtime, paced by a clock.

The same runtime as a live run (fusion order, outputs, history), with a :class:`ReplayClock`
instead of devices: ``speed`` 1 is real time, 0 as fast as possible. At full speed the runtime
runs in lock-step (camera work is awaited at the horizon), so the result does not depend on
the machine: for IMU and GPS it equals the offline ``vtolpose.service.replay.session.replay``.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from pathlib import Path
from typing import Any, AsyncIterator, Callable, Sequence

from vtolpose.drivers.files.dataset import Dataset
from vtolpose.service.runtime.daemon import build_runtime, serve
from vtolpose.estimator import FusedRun, OutputPose
from vtolpose.service.replay.faults import FaultInjector, inject
from vtolpose.service.runtime.loop import CameraProcessor, Runtime, RunSummary
from vtolpose.service.runtime.sources import ReplayClock, ReplaySource
from vtolpose.service.runtime.step_taps import SmoothingPlan
from vtolpose.service.runtime.wiring import config_sections

log = logging.getLogger(__name__)

SENSOR_NAMES = ("imu", "gps", "camera")


def checked_sensors(sensors: Sequence[str]) -> list[str]:
    """``sensors`` as a list, or ValueError naming what is wrong (unknown names, no IMU)."""
    sensors = list(sensors)
    unknown = [s for s in sensors if s not in SENSOR_NAMES]
    if unknown:
        raise ValueError(f"unknown sensor(s) {unknown}; choose from {', '.join(SENSOR_NAMES)}")
    if "imu" not in sensors:
        raise ValueError("the estimator needs the IMU: include 'imu' in the sensors")
    return sensors


async def replay_async(
    dataset: Dataset,
    cfg: dict[str, Any],
    sensors: Sequence[str] | None = None,
    speed: float | None = None,
    trajectory_path: str | Path | None = None,
    camera_processor: CameraProcessor | None = None,
    duration_s: float | None = None,
    stop_after_data_s: float | None = None,
    handle_signals: bool = True,
    measure_latency: bool = False,
    hold: bool = False,
    on_hold: Callable[[str], None] | None = None,
    on_fused: Callable[[OutputPose], None] | None = None,
    faults: FaultInjector | None = None,
    on_progress: Callable[[float], None] | None = None,
    start_at_s: float | None = None,
    prepare: Callable[[Runtime], None] | None = None,
    smoothing: SmoothingPlan | None = None,
    on_fused_run: Callable[[FusedRun], None] | None = None,
) -> tuple[RunSummary, Runtime]:
    """Replay ``dataset`` through a runtime built from ``cfg`` (outputs included); returns its summary.

    ``on_progress``: called with the seconds of data fed so far, from the first IMU sample on.

    ``hold``: after the data, keep the outputs up (queries answered from the history) until stopped.
    ``faults``: played on the stream between the dataset and the runtime (``vtolpose.service.replay.faults``).
    ``start_at_s``: join the recording this far in, as a service restarted in flight would: the
    runtime sees nothing before it (no rest, no stated heading it could know).
    ``prepare``: called with the runtime once it is built, before it runs (e.g. to hook the fixed-lag poses).
    ``smoothing``: who sees the filter's steps (:func:`~vtolpose.service.runtime.daemon.build_runtime`).
    """
    configured = config_sections(cfg).replay
    sensors = checked_sensors(sensors or configured.sensors)
    speed = configured.speed if speed is None else speed
    frames, load = None, None
    if "camera" in sensors:
        if camera_processor is None:
            raise ValueError("camera frames need a feature extractor (camera_processor); replay imu,gps or pass one")
        frames, load = dataset.camera_frames(), dataset.load_frame
        if not frames:
            log.warning("%s: no camera frames in the dataset; replaying IMU and GPS", dataset.root)
    clock = ReplayClock(speed)
    source = ReplaySource(dataset, sensors, clock, stop_after_data_s, frames, load, on_progress, start_at_s)
    origin = source.gps.origin_lla if source.gps is not None else dataset.calibration.gps.origin_lla
    calibration = dataset.calibration
    if start_at_s:
        # The heading a crew stated applied at the recording's start, not to a service joining later.
        calibration = dataclasses.replace(calibration, initial_heading_rad=None, initial_heading_sigma_rad=None)
    runtime = build_runtime(
        cfg, calibration, origin=lambda: origin, trajectory_path=trajectory_path,
        camera_processor=camera_processor, lockstep=speed == 0.0, measure_latency=measure_latency, on_fused=on_fused,
        sensor_now=clock.now_ns, smoothing=smoothing, on_fused_run=on_fused_run,
    )
    if prepare is not None:
        prepare(runtime)
    stream = inject(source, faults) if faults is not None and faults.faults else source
    feed = _then_hold(stream, runtime, on_hold or log.info) if hold else stream
    summary = await serve(runtime, [feed], duration_s, handle_signals)
    return summary, runtime


async def _then_hold(source: AsyncIterator, runtime: Runtime, announce: Callable[[str], None]) -> AsyncIterator:
    """The replay, then the estimate made final and kept on offer (queries) until the run is stopped."""
    async for sample in source:
        yield sample
    runtime.fusion.flush()
    runtime.finish_smoothing()
    if runtime.trajectory is not None:
        runtime.trajectory.flush()
    bounds = runtime.history.bounds()
    announce(f"replay finished; history t_ns {bounds[0] if bounds else None}..{bounds[1] if bounds else None}; "
             "serving until SIGINT/SIGTERM")
    await asyncio.Event().wait()


def run_replay(dataset: Dataset, cfg: dict[str, Any], **kwargs: Any) -> tuple[RunSummary, Runtime]:
    """Synchronous wrapper of :func:`replay_async` (its own event loop)."""
    return asyncio.run(replay_async(dataset, cfg, **kwargs))
