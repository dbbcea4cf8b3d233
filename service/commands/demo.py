"""``vtolpose demo``: the whole chain on a machine with no hardware."""

from __future__ import annotations

import argparse
from pathlib import Path

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.drivers.files.tum import write_tum
from vtolpose.drivers.simulator.lidar import simulate_lidar
from vtolpose.service.commands.common import write_json
from vtolpose.service.mapping.poses import trajectory_window
from vtolpose.service.mapping.side_by_side import MAP_CELL_M, map_side_by_side
from vtolpose.service.replay.progress import Progress
from vtolpose.service.replay.session import replay
from vtolpose.service.replay.report import build_report, summary_lines


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="simulate a flight, replay it through the estimator, print the score",
        description="Simulate a flight (default: the thesis' book rig, 120 s), replay it through the\n"
        "estimator with both state models (thesis: p, v, q; biases: + gyro/accel biases), and\n"
        "print the scores side by side. Files go to --out: the dataset, trajectories, reports.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--scenario", choices=("book", "landfill"), default="book")
    p.add_argument("--duration", type=float, default=120.0, metavar="S")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", default="vtolpose-demo", metavar="DIR", help="output folder (default ./vtolpose-demo)")
    p.add_argument("--lidar", action="store_true", help="also fly the scenario's LIDAR and map the flight with the true "
                   "poses and with each trajectory: height RMSE and volume error side by side")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    data = out / f"{args.scenario}-seed{args.seed}"
    print(f"simulating {args.duration:g} s of the '{args.scenario}' scenario (seed {args.seed}) into {data}")
    flight = simulate_flight(args.scenario, args.duration, args.seed)
    write_flight(flight, data, overwrite=True, lidar=simulate_lidar(flight) if args.lidar else None)
    dataset = Dataset.open(data)
    to_map = {}  # every trajectory the LIDAR map is compared with, by label, in the order printed
    for variant in ("thesis", "biases"):
        cfg = load_config(None, {"estimator": {"variant": variant}})
        progress = Progress(args.duration, f"replay ({variant})")
        result = replay(dataset, cfg, ["imu", "gps"], on_progress=lambda d, t: progress.update(d))
        progress.finish()
        report = build_report(result, dataset, cfg)
        write_tum(out / f"trajectory-{variant}.txt", result.trajectory.t_ns, result.trajectory.p, result.trajectory.q)
        write_json(out / f"report-{variant}.json", report)
        print("\n".join(summary_lines(report)))
        to_map[f"filter ({variant})"] = trajectory_window(result.trajectory.t_ns, result.trajectory.p, result.trajectory.q)
    if args.lidar:
        print()
        print("\n".join(map_side_by_side(dataset, to_map, MAP_CELL_M[args.scenario])[1]))
    print(f"\ntrajectories and reports in {out}/ (score again with: vtolpose eval {out}/trajectory-biases.txt --truth {data})")
    return 0
