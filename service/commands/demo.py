"""``vtolpose demo``: the whole chain on a machine with no hardware."""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path
from typing import TYPE_CHECKING

from vtolpose.config import load_config
from vtolpose.service.commands.common import write_json
from vtolpose.service.replay.progress import Progress

if TYPE_CHECKING:
    from vtolpose.drivers.files.dataset import Dataset

# The sensor sets the LIDAR map compares (default model, biases), by the label its rows carry.
MAP_SENSOR_SETS = {"IMU+GPS": ["imu", "gps"], "IMU+camera+GPS": ["imu", "camera", "gps"]}


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
    p.add_argument("--lidar", action="store_true", help="also fly the scenario's LIDAR, replay the flight with IMU+GPS "
                   "and with IMU+camera+GPS (biases model, smoothed), and map it with the true poses and with each "
                   "sensor set's filtered, fixed-lag (smoothing.fixed_lag_s) and smoothed trajectory: height RMSE, "
                   "bias and volume error side by side, and each trajectory's pose errors at the returns' times")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.drivers.files.tum import write_tum
    from vtolpose.drivers.simulator import simulate_flight
    from vtolpose.drivers.simulator.export import write_flight
    from vtolpose.drivers.simulator.lidar import simulate_lidar
    from vtolpose.drivers.simulator.render import default_camera
    from vtolpose.service.mapping.side_by_side import MAP_CELL_M, map_side_by_side
    from vtolpose.service.replay.report import build_report
    from vtolpose.service.replay.session import replay

    out = Path(args.out)
    data = out / f"{args.scenario}-seed{args.seed}"
    print(f"simulating {args.duration:g} s of the '{args.scenario}' scenario (seed {args.seed}) into {data}")
    flight = simulate_flight(args.scenario, args.duration, args.seed)
    camera = None
    if args.lidar:  # the map compares IMU+camera+GPS too: render the frames it needs
        if importlib.util.find_spec("skimage") is None:
            print("no camera frames (rendering needs scikit-image: pip install -e '.[sim]'): the LIDAR map compares "
                  "IMU+GPS only")
        else:
            camera = default_camera()
            print(f"rendering {int(args.duration * camera.rate_hz)} camera frames ...")
    write_flight(flight, data, overwrite=True, camera=camera, lidar=simulate_lidar(flight) if args.lidar else None)
    dataset = Dataset.open(data)
    reports = {}
    for variant in ("thesis", "biases"):
        cfg = load_config(None, {"estimator": {"variant": variant}})
        progress = Progress(args.duration, f"replay ({variant})")
        result = replay(dataset, cfg, ["imu", "gps"], on_progress=lambda d, t: progress.update(d))
        progress.finish()
        reports[variant] = report = build_report(result, dataset, cfg)
        write_tum(out / f"trajectory-{variant}.txt", result.trajectory.t_ns, result.trajectory.p, result.trajectory.q)
        write_json(out / f"report-{variant}.json", report)
    to_map = smoothed_trajectories(dataset, out, args.duration) if args.lidar else {}
    print()
    for line in comparison_lines(reports):
        print(line)
    if args.lidar:
        print()
        print("\n".join(map_side_by_side(dataset, to_map, MAP_CELL_M[args.scenario])[1]))
    print(f"\ntrajectories and reports in {out}/ (score again with: vtolpose eval {out}/trajectory-biases.txt --truth {data})")
    return 0


def smoothed_trajectories(dataset: Dataset, out: Path, duration_s: float) -> dict:
    """Each sensor set's filtered, fixed-lag and smoothed trajectory (``replay --smooth``), by map label;
    the trajectories (TUM) and reports go to ``out`` too."""
    from vtolpose.drivers.files.tum import write_tum
    from vtolpose.service.mapping.side_by_side import pose_kinds
    from vtolpose.service.replay.report import build_report
    from vtolpose.service.replay.smoothing import replay_smoothed

    cfg = load_config(None, {"estimator": {"variant": "biases"}})
    to_map = {}
    for name, sensors in MAP_SENSOR_SETS.items():
        if "camera" in sensors and not dataset.has_camera:
            continue
        stem = "-".join(sensors)
        progress = Progress(duration_s, f"replay --smooth ({','.join(sensors)})")
        result = replay_smoothed(dataset, cfg, out / f"trajectory-{stem}-smoothed.txt", sensors=sensors,
                                 on_progress=lambda d, t: progress.update(d))
        progress.finish()
        write_json(out / f"report-{stem}-smoothed.json", build_report(result, dataset, cfg))
        to_map.update({f"{name} {kind}": window for kind, window in pose_kinds(result).items()})
        for kind, t in (("filtered", result.trajectory), ("fixed-lag", result.smoothing.fixed_lag)):
            write_tum(out / f"trajectory-{stem}-{kind}.txt", t.t_ns, t.p, t.q)
    return to_map


# (label, report key, format) of each row of the side-by-side table.
ROWS = (
    ("position RMSE [m]", "position_rmse_m", "{:.4f}"),
    ("GPS RMSE [m]", "gps_rmse_m", "{:.4f}"),
    ("position / GPS", "position_rmse_over_gps", "{:.2f}"),
    ("attitude RMSE [deg]", "attitude_rmse_deg", "{:.3f}"),
    ("NEES mean", "nees_mean", "{:.2f}"),
    ("x real time", "realtime_factor", "{:.0f}"),
)


def comparison_lines(reports: dict[str, dict]) -> list[str]:
    """The two state models side by side, and what the rows mean."""
    names = list(reports)
    first = reports[names[0]]
    lines = [f"IMU + GPS (thesis Test 1) on {first['dataset']}, {first['duration_s']:.0f} s:",
             f"  {'':<22}" + "".join(f"{n:>12}" for n in names)]
    for label, key, form in ROWS:
        cells = [form.format(r[key]) if r.get(key) is not None else "n/a" for r in reports.values()]
        lines.append(f"  {label:<22}" + "".join(f"{c:>12}" for c in cells))
    nees = first.get("nees")
    if nees is not None:
        lo, hi = nees["band_per_sample"]
        inside = ", ".join(f"{n} {'inside' if r['nees']['mean_in_band'] else 'OUTSIDE'}" for n, r in reports.items())
        lines.append(f"  NEES 95% band for {nees['dof']} dof: {lo:.2f}-{hi:.2f} ({inside})")
    if first.get("kernels"):
        lines.append(f"  x real time with the {first['kernels']}")
    lines += [
        "thesis: position, velocity, attitude (the thesis' state); biases: the same plus gyro and",
        "accelerometer biases. Position / GPS below 1 means the fusion beats the GPS it was given;",
        "a NEES inside its band means the filter's own uncertainty is honest.",
    ]
    return lines
