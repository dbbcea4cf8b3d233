"""``vtolpose simulate``: a simulated flight with truth, written as a dataset."""

from __future__ import annotations

import argparse

from drivers.simulator import SCENARIOS, simulate_flight
from drivers.simulator.export import write_flight


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="make a simulated flight dataset (IMU, GPS, truth)",
        description="Simulate a flight and write it in the dataset layout that `replay` reads.\n\n"
        "Scenarios:\n"
        "  book      the thesis' rig: a sensor platform carried by a robot arm 0.5-1 m over a table\n"
        "            with a book; tens of centimetres of motion; GPS sigma 2 cm\n"
        "  landfill  a helicopter surveying a landfill at 30-60 m, 8 m/s lawnmower legs; GPS sigma 1 m\n\n"
        "The same scenario, duration and seed always give the same bytes.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--scenario", choices=sorted(SCENARIOS), default="book")
    p.add_argument("--duration", type=float, default=120.0, metavar="S", help="seconds of flight (default 120)")
    p.add_argument("--seed", type=int, default=1, help="noise seed (default 1)")
    p.add_argument("--out", required=True, metavar="DATASET", help="folder to write")
    p.add_argument("--force", action="store_true", help="replace an existing dataset in --out")
    p.add_argument("--no-camera", action="store_true", help="IMU, GPS and truth only: no rendered camera frames")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    flight = simulate_flight(args.scenario, args.duration, args.seed)
    out = write_flight(flight, args.out, overwrite=args.force)
    print(f"wrote {out}: {flight.description}")
    print(f"  imu {len(flight.imu.t_ns)} samples, gps {len(flight.gps.t_ns)} fixes, truth {len(flight.truth.t_ns)} poses")
    return 0
