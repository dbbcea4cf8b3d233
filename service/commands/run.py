"""``vtolpose run``: the onboard daemon (live sensors, or a dataset replayed through the same runtime)."""

from __future__ import annotations

import argparse
import asyncio
import datetime
import logging

from vtolpose.config import ConfigError, load_config
from vtolpose.service.commands.common import add_config_options, overrides_from, parse_sensors
from vtolpose.service.replay.fault_specs import add_fault_options

log = logging.getLogger(__name__)
LIVE_FRAME_REPORTS = 1000  # recent per-frame reports a long run keeps (memory stays flat)
FOXGLOVE_CONFIG_PORT = -1  # --foxglove without a port: outputs.foxglove.port


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="the onboard daemon: sensors in, ODOMETRY (MAVLink) and poses (Zenoh) out",
        description="Run the estimator as a daemon. Sources, estimator and outputs come from the configuration\n"
        "(sensors.*, fusion.*, outputs.*), which is validated before any port is opened. SIGINT or SIGTERM\n"
        "stops it cleanly: the fusion buffer is flushed, the trajectory file completed, links closed.\n\n"
        "--replay feeds a dataset through exactly the same runtime, paced by a clock (--speed 1 is\n"
        "real time, 0 as fast as possible and deterministic).\n\n"
        "Examples:\n"
        "  vtolpose run --config vehicle.yaml\n"
        "  vtolpose run --replay data/landfill --speed 1 --mavlink udpout:127.0.0.1:14540 --zenoh\n"
        "  vtolpose run --replay data/book --out traj.txt       (same trajectory as `vtolpose replay`)\n"
        "  vtolpose run --replay data/landfill --start-at 80 --sensors imu,camera   (restarted in flight)\n"
        "  vtolpose run --replay data/book --speed 1 --foxglove --hold   (watch it in Foxglove: ws://127.0.0.1:8765)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_config_options(p)
    p.add_argument("--replay", metavar="DATASET", help="replay this dataset instead of reading the sensors")
    p.add_argument("--sensors", metavar="LIST", help="replay: streams to use, e.g. imu,gps (replay.sensors)")
    add_start_option(p)
    add_runtime_options(p)
    add_fault_options(p)  # replay only: faults played on the replayed stream (vtolpose.service.replay.faults)
    p.add_argument("--out", metavar="TRAJ.txt", help="write the fused trajectory here (TUM; run.trajectory)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds of wall time")
    p.add_argument("--record", metavar="DIR", help="live: record every raw sample into this new dataset folder; {start} in it becomes the UTC start "
                   "time, e.g. /data/flights/{start} (run.record_dir)")
    p.add_argument("--hold", action="store_true",
                   help="replay: after the data, keep answering queries (pose/at, trajectory) until stopped")
    p.set_defaults(run=run)


def add_start_option(p: argparse.ArgumentParser) -> None:
    """--start-at: join a replayed recording S seconds in, as a service restarted in flight."""
    p.add_argument("--start-at", type=_start_seconds, metavar="S",
                   help="replay: start S seconds into the recording, as a service restarted in flight would "
                        "(nothing before it is seen, and the recording's stated heading no longer applies)")


def _start_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (value >= 0.0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"{text!r}: must be a finite number of seconds >= 0")
    return value


def add_runtime_options(p: argparse.ArgumentParser) -> None:
    """--speed and the output switches: shared by every command that drives the runtime."""
    p.add_argument("--speed", type=float, metavar="X", help="replay speed, x real time; 0 = as fast as possible (replay.speed)")
    p.add_argument("--mavlink", metavar="URL", help="enable the MAVLink output on this link (outputs.mavlink.url)")
    p.add_argument("--zenoh", action="store_true", help="enable the Zenoh output (outputs.zenoh.*)")
    p.add_argument("--ros2", action="store_true",
                   help="publish nav_msgs/Odometry and TF for ROS 2 nodes on rmw_zenoh (outputs.ros2.*)")
    p.add_argument("--foxglove", nargs="?", type=int, const=FOXGLOVE_CONFIG_PORT, metavar="PORT",
                   help="serve the live 3-D view to Foxglove on ws://HOST:PORT (outputs.foxglove.*; default port 8765)")
    p.add_argument("--mcap", metavar="FILE", help="record the view, every estimate, the raw samples and the status "
                   "into this new MCAP file (outputs.mcap.file)")


def config_for(args: argparse.Namespace) -> dict:
    """The configuration with --config, --set and the runtime switches folded in, validated alike."""
    overrides = overrides_from(args)
    outputs = overrides.setdefault("outputs", {})
    if args.mavlink:
        outputs.setdefault("mavlink", {}).update(enabled=True, url=args.mavlink)
    if args.zenoh:
        outputs.setdefault("zenoh", {})["enabled"] = True
    if args.ros2:
        outputs.setdefault("ros2", {})["enabled"] = True
    if args.foxglove is not None:
        view = outputs.setdefault("foxglove", {})
        view["enabled"] = True
        if args.foxglove != FOXGLOVE_CONFIG_PORT:
            view["port"] = args.foxglove
    if args.mcap:
        outputs.setdefault("mcap", {})["file"] = args.mcap
    if args.speed is not None:
        overrides.setdefault("replay", {})["speed"] = args.speed
    if getattr(args, "record", None):
        overrides.setdefault("run", {})["record_dir"] = args.record
    if not outputs:
        del overrides["outputs"]
    return load_config(args.config, overrides)


def recording_folder(template: str, now: datetime.datetime | None = None) -> str:
    """``run.record_dir`` with ``{start}`` replaced by the UTC start time (e.g. 20261122T103105Z), so a
    service that restarts records each flight into its own new folder instead of refusing to start."""
    now = now or datetime.datetime.now(datetime.timezone.utc)
    return template.replace("{start}", now.strftime("%Y%m%dT%H%M%SZ"))


def camera_processor(cfg: dict, calibration):
    """Feature extraction for the runtime's camera workers, or None (with a warning) without intrinsics."""
    from vtolpose.service.replay.session import FrameProcessor
    from vtolpose.service.runtime.wiring import feature_options

    cam = calibration.camera
    if cam is None:
        log.warning("no camera calibration: camera frames are not used")
        return None
    return FrameProcessor(feature_options(cfg), (cam.height, cam.width), keep=LIVE_FRAME_REPORTS)


def run(args: argparse.Namespace) -> int:
    cfg = config_for(args)
    if args.duration is not None and args.duration <= 0:
        raise ConfigError(f"--duration {args.duration}: must be greater than 0")
    from vtolpose.service.runtime.daemon import summary_lines

    if args.replay:
        from vtolpose.drivers.files.dataset import Dataset
        from vtolpose.service.replay.faults import injector_from
        from vtolpose.service.runtime.replay_feed import replay_async
        from vtolpose.service.runtime.wiring import config_sections

        if args.record:
            raise ConfigError("--record writes what live sensors deliver; a replay reads a recording already "
                              "(copy the dataset folder to keep it)")
        sections = config_sections(cfg)
        if sections.run.record_dir:
            log.warning("run.record_dir (%s) is not used with --replay: the dataset is the recording", sections.run.record_dir)

        dataset = Dataset.open(args.replay)
        sensors = parse_sensors(args.sensors) or sections.replay.sensors
        processor = camera_processor(cfg, dataset.calibration) if "camera" in sensors else None
        injector = injector_from(args)
        summary, _ = asyncio.run(replay_async(dataset, cfg, sensors, trajectory_path=args.out, camera_processor=processor,
                                              faults=injector, duration_s=args.duration, hold=args.hold,
                                              on_hold=lambda text: print(text, flush=True), start_at_s=args.start_at))
        for fault in injector.report() if injector is not None else ():
            print(f"fault {fault['spec']}: {fault['samples_affected']} samples dropped or changed", flush=True)
    else:
        if args.fault:
            raise ConfigError("--fault plays faults on a replayed stream: use it with --replay")
        if args.start_at is not None:
            raise ConfigError("--start-at joins a replayed recording later: use it with --replay")
        summary = asyncio.run(_live(cfg, args))
    for line in summary_lines(summary):
        print(line, flush=True)
    return 1 if summary.incomplete else 0  # a requested file not written in full is a failure, said in the last line


async def _live(cfg: dict, args: argparse.Namespace):
    from vtolpose.service.runtime.daemon import build_runtime, load_calibration_file, serve
    from vtolpose.service.runtime.live import live_sources
    from vtolpose.service.runtime.wiring import config_sections, with_gps_origin

    sections = config_sections(cfg)
    if sections.run.calibration_file is None:
        raise ConfigError("key 'run.calibration_file': a live run needs the vehicle's calibration "
                          "(a dataset.yaml-format file, e.g. from a recording made with this vehicle)")
    calibration = load_calibration_file(sections.run.calibration_file)
    if sections.sensors.gps.origin is None and calibration.gps.origin_lla is not None:
        # One local frame for the whole vehicle: the calibration's origin unless the GPS section sets one.
        sections = with_gps_origin(sections, tuple(calibration.gps.origin_lla))
    processor = camera_processor(cfg, calibration) if sections.sensors.camera.type != "none" else None
    runtime = build_runtime(cfg, calibration, trajectory_path=args.out, live=True, camera_processor=processor)
    recorder = None
    if sections.run.record_dir:
        from vtolpose.service.outputs.recorder import FlightRecorder

        recorder = FlightRecorder(recording_folder(sections.run.record_dir), calibration,
                                  description="recorded live by vtolpose run")
        runtime.recorder = recorder
    live = live_sources(sections, runtime, recorder)
    runtime.origin = live.origin
    try:
        summary = await serve(runtime, live.sources, args.duration)
    finally:
        if recorder is not None:
            recorder.close()
    if recorder is not None and recorder.status.startswith("stopped"):
        summary.incomplete.append(f"the flight recording {recorder.root} is incomplete: {recorder.status}")
    return summary
