"""``vtolpose map``: the reference LIDAR mapper, from a trajectory file, the truth, or the service over Zenoh."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from vtolpose.service.commands.common import write_json

WAIT_KINDS = ("filtered", "smoothed")  # mapping.poses.WAIT_KINDS, named here so that --help loads no mapper


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "map",
        help="map a dataset's LIDAR returns with a trajectory (or live poses) and score the map",
        description="Place every LIDAR return of a dataset (mav0/lidar0) with the body pose at that return's own\n"
        "time, grid the points into a height map, and report the height RMSE against the true ground,\n"
        "the volume above a base level against the true volume, and the coverage (the true ground is\n"
        "known for simulated datasets).\n\n"
        "Poses come from a trajectory file (TUM, as `replay --out` writes), from the dataset's truth, or\n"
        "live from a running vtolpose over Zenoh: one `trajectory` query per scan, interpolated per\n"
        "return, as docs/outputs.md tells a mapper to.\n\n"
        "Examples:\n"
        "  vtolpose map data/landfill --trajectory traj.txt --png maps/filter --report map.json\n"
        "  vtolpose map data/landfill --trajectory traj.txt --explain   (what position, attitude and timing cost)\n"
        "  vtolpose map data/landfill --true-poses\n"
        "  vtolpose run --replay data/landfill --zenoh --hold &\n"
        "  vtolpose map --zenoh --connect tcp/127.0.0.1:7448 --lidar-from data/landfill --kind smoothed",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", nargs="?", metavar="DATASET", help="dataset with mav0/lidar0")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--trajectory", metavar="TRAJ.txt", help="poses from this trajectory (TUM, or EuRoC truth CSV)")
    source.add_argument("--true-poses", action="store_true", help="poses from the dataset's truth: what the grid itself costs")
    source.add_argument("--zenoh", action="store_true", help="poses from a running vtolpose over Zenoh")
    p.add_argument("--lidar-from", metavar="DATASET", help="with --zenoh: the dataset whose LIDAR returns to map")
    p.add_argument("--cell", type=float, default=1.0, metavar="M", help="map cell size in metres (default 1; the book rig wants ~0.02)")
    p.add_argument("--base", type=float, default=0.0, metavar="M",
                   help="height of the volume's base level, metres up from the origin (default 0)")
    p.add_argument("--time-offset", type=float, default=0.0, metavar="S",
                   help="added to the LIDAR's stamps to put them on the poses' clock (default 0)")
    p.add_argument("--boresight", metavar="ROLL,PITCH,YAW",
                   help="turn the scanner's mounting by these angles [deg] about the body axes (a boresight correction)")
    p.add_argument("--png", metavar="PREFIX", help="write PREFIX-height.png and, with a true ground, PREFIX-error.png")
    p.add_argument("--report", metavar="R.json", help="write the figures as JSON")
    p.add_argument("--explain", action="store_true",
                   help="with --trajectory on a simulated dataset: also map with the trajectory's position alone, its "
                   "attitude alone, and true poses taken once per scan, to show what each costs")
    z = p.add_argument_group("Zenoh (with --zenoh)")
    z.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="the service's endpoint, e.g. tcp/192.168.1.10:7448 (repeatable)")
    z.add_argument("--prefix", default="vtolpose/vtol1", help="the service's key prefix (default vtolpose/vtol1)")
    z.add_argument("--wait", type=float, default=10.0, metavar="S",
                   help="how long to wait for the service to reach a scan before stopping (default 10 s)")
    z.add_argument("--timeout", type=float, default=2.0, metavar="S", help="per query (default 2 s)")
    z.add_argument("--kind", choices=WAIT_KINDS, default="filtered",
                   help="place a scan once every pose over it is at least filtered (default: ~0.2 s behind the "
                   "service, works whatever its configuration), or only once smoothed (the fixed-lag history, "
                   "~2-3 s behind; needs smoothing.fixed_lag_s > 0 in the service): the better map")
    p.set_defaults(run=run)


def _dataset_path(args: argparse.Namespace) -> str:
    if args.dataset and args.lidar_from and Path(args.dataset) != Path(args.lidar_from):
        raise ValueError("give the dataset once: as DATASET or as --lidar-from")
    path = args.dataset or args.lidar_from
    if not path:
        raise ValueError("which returns to map? give DATASET (or --lidar-from DATASET with --zenoh)")
    return path


def _angles(text: str) -> tuple[float, float, float]:
    try:
        angles = tuple(float(x) for x in text.split(","))
    except ValueError:
        angles = ()
    if len(angles) != 3 or not all(map(math.isfinite, angles)):
        raise ValueError(f"--boresight {text!r}: expected ROLL,PITCH,YAW in degrees, e.g. 0.5,0,0")
    return angles


def run(args: argparse.Namespace) -> int:
    from vtolpose.client import PoseClient
    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.drivers.files.lidar import LIDAR_CSV
    from vtolpose.estimator import height_error, score_map
    from vtolpose.service.mapping.mapper import map_returns, pose_errors, true_ground, with_boresight
    from vtolpose.service.mapping.poses import ZenohPoses, file_window, truth_window, window_poses
    from vtolpose.service.mapping.report import (
        MappedFlight, attribution_sources, map_and_score, score_lines, table_lines,
    )

    if not (args.cell > 0.0):
        raise ValueError(f"--cell {args.cell}: must be a positive number of metres")
    if not math.isfinite(args.time_offset):
        raise ValueError(f"--time-offset {args.time_offset}: must be a finite number of seconds")
    if args.kind != "filtered" and not args.zenoh:
        raise ValueError("--kind says which live poses to wait for: use it with --zenoh")
    if args.explain and not args.trajectory:
        raise ValueError("--explain splits a trajectory's cost: use it with --trajectory")
    dataset = Dataset.open(_dataset_path(args))
    returns = dataset.lidar()
    if returns is None:
        raise FileNotFoundError(f"{dataset.root / LIDAR_CSV}: the dataset has no LIDAR returns "
                                "(simulate one with `vtolpose simulate ... --lidar`)")
    if args.boresight:
        returns = with_boresight(returns, *_angles(args.boresight))
    offset_ns = int(round(args.time_offset * 1e9))
    ground = true_ground(returns)
    if args.explain and ground is None:
        raise ValueError(f"{dataset.root}: --explain needs the true ground of a simulated dataset")
    spec = returns.spec
    print(f"{dataset.meta['name']}: {len(returns)} returns in {len(returns.scan_bounds())} scans from the {spec.model} "
          f"({spec.fov_deg:g}° in {spec.step_deg:g}° steps, {spec.scan_rate_hz:g} scans/s, {1e3 * spec.sweep_s:.1f} ms per sweep)")
    if args.zenoh:
        label = f"live {args.kind} poses from {args.prefix} over Zenoh"
        with PoseClient(args.prefix, connect=args.connect, timeout_s=args.timeout) as client:
            source = ZenohPoses(client, wait_s=args.wait, kind=args.kind)
            live = map_returns(returns, source, args.cell, offset_ns)
            source.close()
        flight = MappedFlight(label, live, score_map(live.grid.snapshot(), args.base, ground))
        print(f"{label}: {source.queries} trajectory queries for {live.scans} scans")
    elif args.true_poses:
        flight = map_and_score("true poses", returns, window_poses(truth_window(dataset)), args.cell, args.base, ground,
                               offset_ns)
    else:
        flight = map_and_score(args.trajectory, returns, window_poses(file_window(args.trajectory)), args.cell, args.base,
                               ground, offset_ns)
    placed = flight.run
    print(f"map from {flight.label}: {placed.scans_placed} of {placed.scans} scans placed "
          f"({placed.returns_placed} returns) in {placed.wall_s:.2f} s; {placed.scans_outside} scans outside the poses"
          + (f"; {placed.scans_not_reached} not reached: {placed.stopped}" if placed.scans_not_reached else ""))
    for line in score_lines(flight.score):
        print(line)
    doc: dict = {"dataset": str(dataset.root), "lidar": spec.model, "map": flight.as_dict()}
    if args.explain:
        estimate, truth = file_window(args.trajectory), truth_window(dataset)
        errors = pose_errors(estimate, truth, returns, args.cell, offset_ns)
        maps = [flight if label == "trajectory" else map_and_score(label, returns, source, args.cell, args.base, ground,
                                                                   offset_ns)
                for label, source in attribution_sources(estimate, truth).items()]
        print("\nwhat the map's error comes from (each map scored against the true ground):")
        for line in table_lines(maps):
            print(line)
        print(f"  the trajectory's pose errors at the returns' times: height mean over the map's "
              f"{errors['cells']} cells {errors['height_error_mean_m']:+.3f} m (over its {errors['returns']} returns "
              f"{errors['height_error_mean_returns_m']:+.3f} m; RMS {errors['height_error_rms_m']:.3f} m), horizontal RMS "
              f"{errors['horizontal_rms_m']:.3f} m, attitude RMS {errors['attitude_rms_deg']:.3f}°")
        print(f"  height mean over the cells × mapped area = {errors['height_error_mean_m'] * flight.score.area_m2:+.0f} m³")
        doc["explain"] = {"maps": [m.as_dict() for m in maps], "pose_errors": errors}
    if args.png:
        from vtolpose.service.mapping.plots import plot_error, plot_height

        hmap = placed.grid.snapshot()
        written = [plot_height(f"{args.png}-height.png", hmap, f"{dataset.meta['name']}: height map ({flight.label})")]
        if ground is not None:
            written.append(plot_error(f"{args.png}-error.png", hmap, height_error(hmap, ground),
                                      f"{dataset.meta['name']}: map − true ground ({flight.label})"))
        print("figures: " + ", ".join(map(str, written)))
    if args.report:
        write_json(args.report, doc)
    return 0
