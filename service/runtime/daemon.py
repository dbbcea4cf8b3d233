"""From validated configuration to a running runtime: outputs, sources, signals.

``vtolpose run`` (live or ``--replay``) and the replay command go through :func:`build_runtime`
and :func:`serve`, so live and replayed data meet the same code from the fusion core outwards.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import time
from pathlib import Path
from typing import Any, AsyncIterator, Callable, Sequence

from vtolpose.config import ConfigError
from vtolpose.config.outputs import zenoh_prefix
from vtolpose.config.sections import FusionSection, OutputsSection, ReplaySection, Sections
from vtolpose.drivers.files.calibration_yaml import CalibrationError, calibration_from_yaml, load_yaml_file
from vtolpose.estimator import Calibration, Estimator, FusedRun, FusionOptions, OutputPose
from vtolpose.service.outputs.trajectory_file import TrajectoryFile
from vtolpose.service.runtime.kernels import load_compiled_kernels
from vtolpose.service.runtime.loop import CameraProcessor, Runtime, RuntimeOptions, RunSummary
from vtolpose.service.runtime.step_taps import SmoothingPlan, StepTaps
from vtolpose.service.text import describe
from vtolpose.service.runtime.wiring import calibration_with_overrides, config_sections, filter_options, imu_range

log = logging.getLogger(__name__)

Origin = tuple[float, float, float] | None


def fusion_options(fusion: FusionSection) -> FusionOptions:
    return FusionOptions(fusion.delay_s, fusion.max_pending, fusion.max_imu_buffer)


def load_calibration_file(path: str | Path) -> Calibration:
    """A vehicle's calibration from a dataset.yaml-format file (``run.calibration_file``)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"key 'run.calibration_file': file {path} not found")
    try:
        doc = load_yaml_file(path)
    except CalibrationError as exc:
        raise ConfigError(f"key 'run.calibration_file': {exc}") from None
    return calibration_from_yaml(doc, str(path))


def replay_camera_workers(replay: ReplaySection) -> int:
    """Frames a full-speed replay extracts at once: ``replay.camera_workers``, 0 meaning two per core
    (while the loop fuses one frame and waits for the next, the others keep every core busy: SIFT on
    book ~5.6 × real time against ~4.9 × with one per core on 2 cores). Lock-step fuses them in time
    order whatever order they finish in, so the result does not change."""
    return replay.camera_workers or max(1, min(2 * (os.cpu_count() or 1), 16))


def build_runtime(
    cfg: dict[str, Any],
    calibration: Calibration,
    *,
    origin: Callable[[], Origin] = lambda: None,
    trajectory_path: str | Path | None = None,
    camera_processor: CameraProcessor | None = None,
    lockstep: bool = False,
    measure_latency: bool = False,
    live: bool = False,
    on_fused: Callable[[OutputPose], None] | None = None,
    sensor_now: Callable[[], int | None] | None = None,
    smoothing: SmoothingPlan | None = None,
    on_fused_run: Callable[[FusedRun], None] | None = None,
) -> Runtime:
    """The estimator, fusion core, history and the outputs enabled in ``outputs.*``.

    ``smoothing``: who sees the filter's steps (a replay's backward pass); without it, a Zenoh output keeps its
    history smoothed after ``smoothing.fixed_lag_s`` (mappers read it). Decided here, before the estimator is
    built, for the estimator is given its recorder at construction.

    ``live``: apply ``run.realtime_priority`` (never to a replay, which would hog a core at it); live sensor
    stamps are on the monotonic clock (ROS 2 stamps and TIMESYNC answers follow from it). ``sensor_now``:
    the sensor clock now, when it is not the monotonic one (a paced replay's); TIMESYNC answers on it.
    """
    sections = config_sections(cfg)
    calibration = calibration_with_overrides(cfg, calibration)
    outputs = sections.outputs
    if smoothing is None and outputs.zenoh.enabled:
        s = sections.smoothing
        smoothing = SmoothingPlan(s.fixed_lag_s, s.steps_per_sample, s.max_window_s)
    taps = StepTaps(smoothing) if smoothing is not None and smoothing.records else None
    estimator = Estimator(calibration, filter_options(cfg, calibration.imu.noise), recorder=taps.recorder if taps else None)
    options = RuntimeOptions(
        fusion=fusion_options(sections.fusion), history_s=outputs.zenoh.history_s,
        camera_workers=1 if getattr(camera_processor, "in_order", False) else (
            replay_camera_workers(sections.replay) if lockstep else sections.fusion.camera_workers),
        camera_process=sections.replay.camera_process if lockstep else sections.fusion.camera_process,
        lockstep=lockstep, measure_latency=measure_latency, update_thread=sections.fusion.update_thread and not lockstep,
        realtime_priority=sections.run.realtime_priority if live else None, imu_range=imu_range(cfg),
    )
    path = trajectory_path or sections.run.trajectory
    runtime = Runtime(estimator, options, camera_processor=camera_processor,
                      trajectory=TrajectoryFile(path) if path else None, on_fused=on_fused, taps=taps,
                      on_fused_run=on_fused_run)
    runtime.origin = origin  # replaceable later (a live GPS fixes its origin at its first fix)
    if outputs.mavlink.enabled:
        from vtolpose.service.outputs.mavlink_output import MavlinkOutput, SensorClock

        now = sensor_now if sensor_now is not None else time.monotonic_ns if live else None
        try:
            runtime.outputs.append(MavlinkOutput.from_section(outputs.mavlink, sections.vehicle.system_id,
                                                              SensorClock(now=now)))
        except ValueError as exc:  # an unusable signing key file: the message names its key
            raise ConfigError(str(exc)) from None
    if outputs.zenoh.enabled:
        add_zenoh_output(runtime, sections)
    add_interop_outputs(runtime, outputs, camera_processor, live)
    load_compiled_kernels(runs=runtime.fuses_runs)  # now, not on the first IMU step or fix
    return runtime


def add_zenoh_output(runtime: Runtime, sections: Sections) -> None:
    """Poses and history queries over Zenoh (``outputs.zenoh``); :func:`build_runtime` keeps the history smoothed."""
    from vtolpose.service.outputs.zenoh import QueryLimits, ZenohOutput
    from vtolpose.service.outputs.zenoh_session import ZenohSettings

    zenoh = sections.outputs.zenoh
    prefix = zenoh_prefix(zenoh.prefix, sections.vehicle.name)
    answers = None
    if zenoh.query_process:  # the answers made off the service's interpreter, from a copy of the history
        from vtolpose.service.outputs.zenoh_answers import QueryProcess

        answers = QueryProcess(zenoh.history_s)
        runtime.history_feed = answers.feed
    runtime.outputs.append(ZenohOutput(ZenohSettings.from_section(zenoh), prefix, runtime.history, runtime.history_lock,
                                       lambda: runtime.origin(), QueryLimits.from_section(zenoh), answers))


def add_interop_outputs(runtime: Runtime, outputs: OutputsSection, camera_processor: CameraProcessor | None,
                        live: bool = False) -> None:
    """ROS 2 over Zenoh, the Foxglove view and the MCAP recording (``outputs.ros2|foxglove|mcap``); the
    latter two also see raw samples (``Runtime.sample_taps``) and camera frames (the processor's ``on_frame``)."""
    origin = lambda: runtime.origin()  # noqa: E731 - read late: a live GPS fixes its origin at its first fix
    if outputs.ros2.enabled:
        from vtolpose.service.outputs.ros2 import Ros2Output
        from vtolpose.service.outputs.zenoh_session import ZenohSettings

        zenoh_out = next((o for o in runtime.outputs if o.name == "zenoh"), None)  # opened before this one
        runtime.outputs.append(Ros2Output(outputs.ros2, ZenohSettings.from_section(outputs.zenoh),
                                          lambda: zenoh_out.session if zenoh_out is not None else None,
                                          live=live))
    viewers: list[Any] = []
    foxglove, mcap_file = outputs.foxglove, outputs.mcap.file
    if foxglove.enabled or mcap_file:
        from vtolpose.service.outputs.foxglove import FoxgloveOutput, estimator_landmarks

        view = dict(rate_hz=foxglove.rate_hz, path_points=foxglove.path_points,
                    origin=origin, landmarks=lambda: estimator_landmarks(runtime.est))
        if foxglove.enabled:
            viewers.append(FoxgloveOutput(foxglove.host, foxglove.port, **view))
        if mcap_file:
            from vtolpose.service.outputs.mcap import McapOutput

            viewers.append(McapOutput(mcap_file, **view))
    runtime.outputs += viewers
    runtime.sample_taps += [v.on_sample for v in viewers]
    if viewers and camera_processor is not None and hasattr(camera_processor, "on_frame"):
        before = camera_processor.on_frame  # e.g. the replay's overlay pictures

        def on_frame(*frame: Any) -> None:
            if before is not None:
                before(*frame)
            for viewer in viewers:
                try:
                    viewer.on_frame(*frame)
                except Exception as exc:  # a viewer's failure must not fail the camera update it watches
                    runtime.failures.record(f"output {viewer.name} frame", exc)

        camera_processor.on_frame = on_frame


async def serve(
    runtime: Runtime,
    sources: Sequence[AsyncIterator],
    duration_s: float | None = None,
    handle_signals: bool = True,
) -> RunSummary:
    """Run until the sources end, ``duration_s`` passes, or SIGINT/SIGTERM; then shut down cleanly."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    installed = []
    if handle_signals:
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                loop.add_signal_handler(sig, stop.set)
                installed.append(sig)
            except (NotImplementedError, RuntimeError) as exc:  # not the main thread, or no signals here
                log.debug("signal %s not handled here (%s): stop the run by its stop event", sig.name, exc)
    try:
        return await runtime.run(sources, stop, duration_s)
    finally:
        for sig in installed:
            loop.remove_signal_handler(sig)


def summary_lines(summary: RunSummary) -> list[str]:
    lines = [
        f"stopped by {summary.stopped_by} after {summary.wall_s:.1f} s: {summary.imu_samples} IMU samples "
        f"({summary.data_s:.1f} s of data), {summary.poses_published} poses published, "
        f"{summary.trajectory_lines} trajectory lines",
    ]
    if summary.latency_ms["p50"] == summary.latency_ms["p50"]:  # not NaN
        lines.append("latency IMU in -> outputs out: p50 {p50:.3f} ms, p99 {p99:.3f} ms, max {max:.3f} ms".format(**summary.latency_ms))
    status = summary.status
    if status.get("rejected"):
        lines.append(f"rejected by the filter: {describe(status['rejected'])}")
    if status["fusion"]["rejected"]:
        lines.append(f"refused by the fusion order: {describe(status['fusion']['rejected'])}")
    if status.get("events"):
        lines.append(f"runtime events: {describe(status['events'])}")
    health = status.get("health") or {}
    if health.get("resets"):
        last = health["last_reset"]
        lines.append(f"filter resets: {describe(health['resets'])}; the last: {last['reason']}")
    if health.get("degraded"):
        lines.append(f"degraded at the end: {', '.join(health['degraded'])}")
    noise = status.get("gps_noise") or {}
    if noise.get("fixes_adjusted"):
        lines.append(f"GPS accuracy claims not believed: {noise['fixes_adjusted']} fixes weighed with the noise measured"
                     + (f"; at the end: {noise['text']}" if noise.get("text") else ""))
    if status.get("failures"):
        lines.append("isolated failures: " + "; ".join(f"{part} x{f['failures']} ({f['last']})"
                                                    for part, f in status["failures"].items()))
    return lines + summary.incomplete  # last: what was asked for and not done (the command then fails)
