"""``vtolpose batch``: many flights smoothed, mapped and scored, on this computer or a Dask cluster."""

from __future__ import annotations

import argparse
import importlib.util
import logging
import sys
from pathlib import Path
from typing import Any, TextIO

from vtolpose.service.commands.common import add_config_options, parse_sensors
from vtolpose.service.commands.importer import _fix_sigma
from vtolpose.service.replay.progress import _duration


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "batch",
        help="smooth, map and score many flights at once (this computer's cores or a Dask cluster)",
        description="Per flight: import it where needed (EuRoC folders, ROS 2 bags), replay it with --smooth, map it\n"
        "where it has LIDAR, score it where it has truth, and write its trajectories, report and map into\n"
        "OUT/FLIGHT/. Then the fleet table (OUT/fleet.parquet, OUT/fleet.csv: duration, distance, resets,\n"
        "quality over time, GPS rejects, position and volume figures) and a one-page summary (OUT/fleet.html).\n\n"
        "Flights run as tasks of Dask's distributed scheduler: by default a local cluster of one worker\n"
        "process per core (nothing to start); --scheduler runs them on a cluster you already have (docs/batch.md).\n"
        "A flight whose inputs and settings have not changed since it was last done is not run again (--force\n"
        "runs it); a flight that fails is listed with its error and the others go on.\n\n"
        "Examples:\n"
        "  vtolpose batch data/landfill-* --out results\n"
        "  vtolpose batch survey/*.mcap --imu-topic /imu/data --gps-topic /fix --out results --workers 2\n"
        "  vtolpose batch ../shared/data/euroc_mh01 --gps-rate 10 --out results\n"
        "  vtolpose batch /shared/flights/* --out /shared/results --scheduler tcp://10.0.0.5:8786",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("flights", nargs="+", metavar="FLIGHT", help="dataset folders, EuRoC folders, rosbag2 folders or "
                   ".mcap files; globs are expanded (quote them on a cluster so every path is read where it is)")
    p.add_argument("--out", required=True, metavar="RESULTS", help="output folder: one folder per flight, the table, the summary")
    add_config_options(p)
    p.add_argument("--sensors", metavar="LIST", help="comma-separated streams to use (default: replay.sensors); a "
                   "flight without one of them runs without it and its report says so")
    p.add_argument("--score-from", metavar="S", type=float, default=0.0,
                   help="score accuracy from S seconds after the truth starts (default 0)")
    p.add_argument("--cell", type=float, default=1.0, metavar="M", help="map cell size in metres (default 1)")
    p.add_argument("--base", type=float, default=0.0, metavar="M", help="volume base level, metres up from the origin (default 0)")
    p.add_argument("--force", action="store_true", help="run every flight, even those done with the same inputs and settings")
    p.add_argument("--no-plots", action="store_true", help="no map PNGs and no figures in the summary")
    p.add_argument("--no-progress", action="store_true", help="no progress line even on a terminal")
    engine = p.add_argument_group("where the flights run")
    engine.add_argument("--scheduler", metavar="tcp://HOST:8786", help="a running Dask scheduler (default: a local "
                        "cluster for this batch)")
    engine.add_argument("--workers", type=int, metavar="N", help="local cluster: worker processes, one flight each at a "
                        "time (default: one per core)")
    engine.add_argument("--memory-limit", metavar="SIZE", help="local cluster: memory per worker, e.g. 4GB (default: "
                        "the machine's memory shared among the workers); a flight above it is stopped and listed as failed")
    imports = p.add_argument_group("importing EuRoC folders and bags (vtolpose import's options)")
    imports.add_argument("--gps-rate", type=float, metavar="HZ", help="EuRoC: make a GPS at this rate from the truth")
    imports.add_argument("--gps-sigma", type=float, default=0.02, metavar="M", help="EuRoC: its horizontal sigma (default 0.02)")
    imports.add_argument("--seed", type=int, default=0, help="EuRoC: GPS noise seed (default 0)")
    imports.add_argument("--mounting", metavar="YAML", help="EuRoC: IMU mounting and truth frame")
    imports.add_argument("--no-camera", action="store_true", help="EuRoC: leave mav0/cam0 out")
    imports.add_argument("--imu-topic", metavar="TOPIC", help="bags: sensor_msgs/Imu topic")
    imports.add_argument("--gps-topic", metavar="TOPIC", help="bags: sensor_msgs/NavSatFix topic")
    imports.add_argument("--image-topic", metavar="TOPIC", help="bags: Image or CompressedImage topic")
    imports.add_argument("--truth-topic", metavar="TOPIC", help="bags: PoseStamped or Odometry truth")
    imports.add_argument("--calibration", metavar="YAML", help="bags: the vehicle's calibration (dataset.yaml format)")
    imports.add_argument("--fix-sigma", metavar="H[,V]", help="bags: GPS sigma for fixes without a covariance")
    p.set_defaults(run=run)


class BatchDisplay:
    """A line per finished flight on stdout; on a terminal also a status line (done / running / failed, ETA)."""

    def __init__(self, total: int, stream: TextIO | None = None, enabled: bool | None = None) -> None:
        self.total = total
        self.stream = stream or sys.stderr
        self.live = self.stream.isatty() if enabled is None else enabled

    def status(self, state) -> str:
        eta = state.eta_s()
        return (f"batch: {state.finished}/{state.total} finished ({state.done} run, {state.skipped} unchanged, "
                f"{state.failed} failed), {state.running} running, eta {'--' if eta is None else _duration(eta)}")

    def __call__(self, state, row: dict[str, Any]) -> None:
        if self.live:
            self.stream.write("\r\033[K")
        what = {"done": f"done in {row.get('wall_s', 0):.1f} s", "skipped": "unchanged, not run again",
                "failed": f"FAILED: {row.get('error')}"}[row["status"]]
        print(f"  [{state.finished}/{state.total}] {row['flight']}: {what}", flush=True)
        if self.live:
            self.stream.write(self.status(state))
            self.stream.flush()

    def finish(self) -> None:
        if self.live:
            self.stream.write("\n")
            self.stream.flush()


def settings_from(args: argparse.Namespace):
    from vtolpose.service.batch.settings import BagImport, BatchSettings, EurocImport
    from vtolpose.service.commands.common import config_from

    if not (args.cell > 0.0):
        raise ValueError(f"--cell {args.cell}: must be a positive number of metres")
    for name in ("mounting", "calibration"):
        value = getattr(args, name)
        if value is not None and not Path(value).is_file():
            raise FileNotFoundError(f"--{name} {value}: file not found")
    sensors = parse_sensors(args.sensors)
    plots = not args.no_plots and importlib.util.find_spec("matplotlib") is not None
    return BatchSettings(
        config_from(args), tuple(sensors) if sensors else None, args.score_from, args.cell, args.base, plots,
        EurocImport(args.gps_rate, args.gps_sigma, args.seed, args.mounting and str(Path(args.mounting).absolute()),
                    not args.no_camera),
        BagImport(args.imu_topic, args.gps_topic, args.image_topic, args.truth_topic,
                  args.calibration and str(Path(args.calibration).absolute()), _fix_sigma(args.fix_sigma)),
    )


def run(args: argparse.Namespace) -> int:
    from vtolpose.service.batch.engine import run_batch
    from vtolpose.service.batch.flights import find_flights
    from vtolpose.service.batch.summary import write_summary
    from vtolpose.service.batch.table import write_tables

    if not getattr(args, "verbose", False):  # the scheduler's and nannies' start-up chatter: with -v only
        import distributed  # noqa: F401 - its import sets its loggers' levels, which this then lowers

        logging.getLogger("distributed").setLevel(logging.WARNING)
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers {args.workers}: must be at least 1")
    if args.scheduler and (args.workers or args.memory_limit):
        raise ValueError("--workers and --memory-limit size the local cluster; a --scheduler's cluster has its own "
                         "(set them where its workers start: dask worker --nthreads 1 --memory-limit ...)")
    settings = settings_from(args)
    flights = find_flights(args.flights)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"batch: {len(flights)} flights into {out}" + (f" on {args.scheduler}" if args.scheduler else ""))
    if not settings.plots and not args.no_plots:
        print("  (no figures: drawing them needs matplotlib, the 'plot' extra)")
    display = BatchDisplay(len(flights), enabled=False if args.no_progress else None)
    outcome = run_batch(flights, settings, out, args.scheduler, args.workers, args.memory_limit, args.force, display)
    display.finish()
    parquet, csv_path = write_tables(outcome.rows, out)
    html = write_summary(outcome.rows, out, outcome.where, outcome.wall_s, settings.plots)
    failed = [r for r in outcome.rows if r["status"] == "failed"]
    counts = {s: sum(r["status"] == s for r in outcome.rows) for s in ("done", "skipped")}
    print(f"batch: {counts['done']} run, {counts['skipped']} unchanged, {len(failed)} failed, in "
          f"{_duration(outcome.wall_s)} on {outcome.where}")
    for row in failed:
        print(f"  failed: {row['flight']} ({row['input']}): {row['error']}")
    print(f"  wrote {parquet}, {csv_path} and {html}")
    return 1 if failed else 0
