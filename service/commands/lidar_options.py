"""``--lidar`` and the scanner's figures, for ``simulate`` and ``demo``."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from vtolpose.drivers.files.lidar import LidarReturns
    from vtolpose.drivers.simulator.flight import SimulatedFlight


def add_lidar_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("LIDAR (with --lidar; defaults: the scenario's scanner, docs/mapping.md)")
    g.add_argument("--lidar", action="store_true",
                   help="add a line-scanning LIDAR (landfill: a survey scanner; book: the URG-04LX) as mav0/lidar0")
    g.add_argument("--lidar-fov", type=float, metavar="DEG", help="field of view (landfill 90, book 240)")
    g.add_argument("--lidar-step", type=float, metavar="DEG", help="angular step (landfill 0.25, book 0.3516)")
    g.add_argument("--lidar-rate", type=float, metavar="HZ", help="scans per second (10 for both)")
    g.add_argument("--lidar-range-sigma", type=float, metavar="M", help="range noise 1-sigma (landfill 0.02, book 0.01)")
    g.add_argument("--lidar-max-range", type=float, metavar="M", help="maximum range (landfill 150, book 4)")


def lidar_from_args(args: argparse.Namespace, flight: SimulatedFlight) -> LidarReturns | None:
    """The flight's LIDAR returns when ``--lidar`` was given (figures from the options over the scenario's scanner)."""
    if not args.lidar:
        return None
    from vtolpose.drivers.simulator.lidar import default_lidar, lidar_with, simulate_lidar

    spec = lidar_with(default_lidar(flight.scenario_name), fov_deg=args.lidar_fov, step_deg=args.lidar_step,
                      scan_rate_hz=args.lidar_rate, range_sigma_m=args.lidar_range_sigma,
                      max_range_m=args.lidar_max_range)
    return simulate_lidar(flight, spec)
