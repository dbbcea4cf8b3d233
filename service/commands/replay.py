"""``vtolpose replay``: the estimator over a recorded or simulated dataset."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from vtolpose.service.commands.common import add_config_options, parse_sensors, write_json
from vtolpose.service.commands.run import add_runtime_options, add_start_option, config_for
from vtolpose.service.replay.fault_specs import add_fault_options, parse_faults

if TYPE_CHECKING:
    from vtolpose.drivers.files.dataset import Dataset

log = logging.getLogger(__name__)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay",
        help="run the estimator over a dataset, write the trajectory and a report",
        description="Replay a dataset through the onboard runtime (the same one `vtolpose run` uses), as\n"
        "fast as the machine allows or paced with --speed, optionally with the MAVLink and Zenoh\n"
        "outputs switched on. Writes the filtered trajectory (TUM: t x y z qx qy qz qw, NED/FRD; with --smooth the\n"
        "smoothed one, docs/smoothing.md) and a JSON report with\n"
        "accuracy against the dataset's truth (if any), consistency (NEES), speed and every\n"
        "fused/rejected measurement count.\n\n"
        "Sensor sets: imu,gps (thesis Test 1); imu,camera (Test 2); imu,camera,gps (Test 3).\n\n"
        "Examples:\n"
        "  vtolpose replay data/book --sensors imu,gps --variant thesis --out traj.txt --report report.json\n"
        "  vtolpose replay data/landfill --speed 1 --mavlink udpout:127.0.0.1:14540 --zenoh   (a live-like feed)\n"
        "  vtolpose replay data/landfill --sensors imu,camera,gps --fault gps-off:60:30 --report r.json\n"
        "  vtolpose replay data/book --sensors imu,camera,gps --speed 1 --foxglove --mcap book.mcap\n"
        "  vtolpose replay data/mh01 --smooth --out smoothed.txt --cov smoothed_cov.csv --report r.json --score-from 15",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", metavar="DATASET", help="dataset folder (docs/configuration.md, Datasets)")
    add_config_options(p)
    add_runtime_options(p)
    add_fault_options(p)
    p.add_argument("--sensors", metavar="LIST", help="comma-separated streams to use (default: replay.sensors)")
    add_start_option(p)
    p.add_argument("--out", metavar="TRAJ.txt", help="trajectory file (TUM format); with --smooth the smoothed one")
    p.add_argument("--report", metavar="REPORT.json", help="JSON report")
    p.add_argument("--smooth", action="store_true", help="also run the Rauch-Tung-Striebel backward pass: --out gets the "
                   "smoothed trajectory, the report scores filtered, smoothed and fixed-lag (smoothing.fixed_lag_s) poses "
                   "side by side")
    p.add_argument("--filtered-out", metavar="TRAJ.txt", help="with --smooth: the filtered trajectory (TUM) too")
    p.add_argument("--cov", metavar="COV.csv", help="with --smooth: the smoothed pose covariance per pose, one line each "
                   "(t, upper triangle of the 6x6 over position and attitude)")
    p.add_argument("--score-from", metavar="S", type=float, default=0.0,
                   help="score accuracy and NEES from S seconds after the truth starts (default 0: all of it)")
    p.add_argument("--overlay", metavar="DIR", help="write a PNG per camera frame into DIR: features, predicted "
                   "landmarks with their search gate, accepted matches with landmark ids")
    p.add_argument("--no-progress", action="store_true", help="no progress display even on a terminal")
    p.set_defaults(run=run)


def requested_sensors(args: argparse.Namespace, cfg: dict, dataset: Dataset) -> list[str]:
    """The sensors to replay: those named with --sensors must all be in the dataset (an error
    says which is missing); --overlay without --sensors adds the camera, since it draws frames."""
    from vtolpose.service.runtime.wiring import config_sections
    from vtolpose.service.replay.session import missing_sensor

    named = parse_sensors(args.sensors)
    if named is None:
        sensors = list(config_sections(cfg).replay.sensors)
        if args.overlay and "camera" not in sensors:
            sensors.append("camera")
    else:
        sensors = named
        if args.overlay and "camera" not in sensors:
            raise ValueError(f"--overlay draws the camera frames, but --sensors {args.sensors} has no camera: "
                             f"add it, e.g. --sensors {','.join([*sensors, 'camera'])}")
    for name in sensors if named is not None or args.overlay else ():
        if name in ("gps", "camera"):
            reason = missing_sensor(dataset, name)
            if reason is not None:
                asked = f"--sensors {args.sensors}" if named is not None else "--overlay"
                raise ValueError(f"{dataset.root}: {asked} needs the {name}: {reason}")
    return sensors


def run(args: argparse.Namespace) -> int:
    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.drivers.files.tum import write_tum
    from vtolpose.service.replay.progress import Progress
    from vtolpose.service.replay.report import build_report, event_lines, summary_lines
    from vtolpose.service.replay.session import replay
    from vtolpose.service.replay.smoothing import replay_smoothed

    cfg = config_for(args)
    faults = parse_faults(args.fault)
    progress = Progress(None, f"replay {Path(args.dataset).name}", enabled=False if args.no_progress else None)
    dataset = Dataset.open(args.dataset)
    sensors = requested_sensors(args, cfg, dataset)

    def on_progress(done_s: float, total_s: float) -> None:
        progress.total = max(total_s, 1e-9)
        progress.update(done_s)

    if (args.filtered_out or args.cov) and not args.smooth:
        raise ValueError("--filtered-out and --cov come with --smooth (without it, --out is the filtered trajectory)")
    overlay = None
    if args.overlay:
        from vtolpose.service.replay.overlay import OverlayWriter  # OpenCV, loaded only to draw

        overlay = OverlayWriter(args.overlay)
    run_args = dict(on_progress=on_progress if progress.enabled else None, on_frame=overlay, faults=faults,
                    fault_seed=args.fault_seed, start_at_s=args.start_at)
    if args.smooth:
        result = replay_smoothed(dataset, cfg, args.out, args.cov, sensors=sensors, **run_args)
    else:
        result = replay(dataset, cfg, sensors, **run_args)
    progress.finish()
    report = build_report(result, dataset, cfg, args.score_from)
    filtered_out = args.filtered_out if args.smooth else args.out
    incomplete = list(result.incomplete)  # each requested file not written in full: said last, and the command fails
    if filtered_out:
        incomplete += written_or_why(f"the trajectory {filtered_out}", write_tum, filtered_out, result.trajectory.t_ns,
                                     result.trajectory.p, result.trajectory.q)
    if args.report:
        incomplete += written_or_why(f"the report {args.report}", write_json, args.report, report)
    for line in event_lines(report) + summary_lines(report):
        print(line)
    if overlay is not None:
        print(f"  overlay: {overlay.written} pictures in {overlay.folder}")
    written = ([f"{'smoothed ' if args.smooth else ''}trajectory {args.out}"] if args.out else [])
    written += [f"filtered trajectory {args.filtered_out}"] if args.smooth and args.filtered_out else []
    written += ([f"covariances {args.cov}"] if args.cov else []) + ([f"report {args.report}"] if args.report else [])
    if incomplete:
        for line in incomplete:
            print(line, flush=True)
        return 1
    print(f"  wrote {' and '.join(written)}" if written else
          "  (nothing written: give --out TRAJ.txt for the trajectory, --report R.json for the full report)")
    return 0


def written_or_why(what: str, write, *args) -> list[str]:
    """Write a requested file; [] when done, else the line that says why it is not (a full disk), the others
    still written."""
    try:
        write(*args)
    except OSError as exc:
        return [f"{what} is incomplete: {exc.strerror or exc}"]
    return []
