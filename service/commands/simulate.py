"""``vtolpose simulate``: a simulated flight with truth, written as a dataset."""

from __future__ import annotations

import argparse
import importlib.util
import time

from vtolpose.service.commands.lidar_options import add_lidar_options, lidar_from_args

SCENARIO_NAMES = ("book", "landfill")  # the simulator's SCENARIOS, named here so that --help loads no simulator


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="make a simulated flight dataset (IMU, GPS, camera frames, truth)",
        description="Simulate a flight and write it in the dataset layout that `replay` reads.\n\n"
        "Scenarios:\n"
        "  book      the thesis' rig: a sensor platform carried by a robot arm 0.5-1 m over a table\n"
        "            with a book; tens of centimetres of motion; GPS sigma 2 cm\n"
        "  landfill  a helicopter surveying a landfill at 30-60 m, 8 m/s lawnmower legs; GPS sigma 1 m\n\n"
        "Camera frames (656 x 494 grey at 7.5 Hz, looking down, rendered from the true pose over the\n"
        "scenario's textured ground) are written when scikit-image is installed (the 'sim' extra);\n"
        "--no-camera skips them.\n\n"
        "--start-in-flight begins the recording in the air, mid-trajectory, with no rest and no stated\n"
        "heading (a service restarted in flight): book 20 s into the arm's motion, landfill on the first\n"
        "survey leg 5 s before a turn (70 s in); a number of seconds picks another point.\n\n"
        "The same scenario, duration and seed always give the same bytes.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--scenario", choices=SCENARIO_NAMES, default="book")
    p.add_argument("--duration", type=float, default=120.0, metavar="S", help="seconds of flight (default 120)")
    p.add_argument("--seed", type=int, default=1, help="noise seed (default 1)")
    p.add_argument("--out", required=True, metavar="DATASET", help="folder to write")
    p.add_argument("--force", action="store_true", help="replace an existing dataset in --out")
    p.add_argument("--no-camera", action="store_true", help="do not render camera frames")
    start = p.add_mutually_exclusive_group()
    start.add_argument("--start-in-flight", nargs="?", type=_seconds, const=-1.0, default=None, metavar="S",
                       help="start S seconds into the scenario's trajectory, moving (default: the scenario's in-flight point)")
    start.add_argument("--rest", type=float, metavar="S", help="seconds at rest on the ground before the motion (default: "
                       "the scenario's, 10 s); e.g. --rest 600 for a record that `calibrate imu` can use")
    add_lidar_options(p)
    p.set_defaults(run=run)


def _seconds(text: str) -> float:
    value = float(text)
    if not (value >= 0.0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"{text!r}: must be a finite number of seconds >= 0")
    return value


def run(args: argparse.Namespace) -> int:
    from vtolpose.drivers.files.dataset import refuse_existing_dataset
    from vtolpose.drivers.simulator import SimulationOptions, make_scenario, simulate_flight
    from vtolpose.drivers.simulator.export import write_flight
    from vtolpose.drivers.simulator.render import default_camera

    refuse_existing_dataset(args.out, args.force)
    options = SimulationOptions(rest_s=args.rest)
    if args.start_in_flight is not None:
        start_s = make_scenario(args.scenario).in_flight_s if args.start_in_flight < 0.0 else args.start_in_flight
        options = SimulationOptions(start_s=start_s)
    flight = simulate_flight(args.scenario, args.duration, args.seed, options)
    camera = None
    if not args.no_camera:
        if importlib.util.find_spec("skimage") is None:
            print("no camera frames: rendering needs scikit-image (pip install scikit-image; from a checkout: pip install -e '.[sim]'); use --no-camera to silence this")
        else:
            camera = default_camera()
            print(f"rendering {int(args.duration * camera.rate_hz)} camera frames "
                  f"({camera.width} x {camera.height} at {camera.rate_hz:g} Hz) ...")
    lidar = lidar_from_args(args, flight)
    started = time.perf_counter()
    out = write_flight(flight, args.out, overwrite=args.force, camera=camera, lidar=lidar)
    print(f"wrote {out}: {flight.description}")
    frames = f", camera frames in {time.perf_counter() - started:.1f} s" if camera is not None else ", no camera"
    scans = f", lidar {len(lidar)} returns ({lidar.spec.model})" if lidar is not None else ""
    print(f"  imu {len(flight.imu.t_ns)} samples, gps {len(flight.gps.t_ns)} fixes, truth {len(flight.truth.t_ns)} poses{frames}{scans}")
    return 0
