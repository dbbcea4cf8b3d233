"""The ``vtolpose`` command line: one entry point, one subcommand per job."""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
import textwrap

# One BLAS thread: the estimator's matrices are small, and idle BLAS threads spin on the core
# that feature extraction needs. Set before anything imports numpy.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from vtolpose.config import ConfigError

# Subcommand name -> its one-line help. Each has a module in vtolpose.service.commands providing
# add_parser(subparsers) and run(args); only the one a command line names is imported (a subcommand's module
# imports what its job needs, and `vtolpose --help` needs none of it). tests/test_cli.py holds these lines to
# the modules' own.
COMMANDS = {
    "demo": "simulate a flight, replay it through the estimator, print the score",
    "simulate": "make a simulated flight dataset (IMU, GPS, camera frames, truth)",
    "import": "convert external data (EuRoC, ROS 2 bags) into a dataset",
    "replay": "run the estimator over a dataset, write the trajectory and a report",
    "eval": "score a trajectory against truth (RMSE, drift)",
    "map": "map a dataset's LIDAR returns with a trajectory (or live poses) and score the map",
    "batch": "smooth, map and score many flights at once (this computer's cores or a Dask cluster)",
    "export": "a TUM trajectory as a WGS84 flight path with time and quality per point (GeoJSON, KML)",
    "bench": "speed figures on this machine (can it keep up?)",
    "calibrate": "calibrate IMU, camera, IMU-camera and GPS timing, GPS lever arm",
    "probe": "field check of one sensor: identity, rate, first samples, packet statistics",
    "run": "the onboard daemon: sensors in, ODOMETRY (MAVLink) and poses (Zenoh) out",
    "warmup": "compile the estimator's kernels once (about half a minute), so no run waits for them",
}

DESCRIPTION = """\
vtolpose: pose of a VTOL UAV from IMU, camera and GPS (EKF-SLAM), for the flight controller
(MAVLink) and a LIDAR mapper (Zenoh).

Start here:
  vtolpose demo                      simulate a flight, replay it, print the score
  vtolpose simulate --scenario book --duration 120 --seed 1 --out data/book
  vtolpose replay data/book --out traj.txt --report report.json
  vtolpose eval traj.txt --truth data/book
  vtolpose bench                     can this computer keep up?
"""


def command_module(name: str):
    """The module of subcommand ``name`` (``import`` lives in ``importer``: a module may not be called import)."""
    return importlib.import_module(f"vtolpose.service.commands.{'importer' if name == 'import' else name}")


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; the subcommands ``argv`` names (all when None) in full, the others by their help line only."""
    wanted = set(COMMANDS) if argv is None else {a for a in argv if a in COMMANDS}
    parser = argparse.ArgumentParser(prog="vtolpose", description=DESCRIPTION, formatter_class=HelpFormatter)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, summary in COMMANDS.items():
        if name in wanted:
            command_module(name).add_parser(sub)
        else:
            sub.add_parser(name, help=summary, add_help=False)
    for command in sub.choices.values():
        finish_subcommand(command)
    return parser


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions as written; option help wrapped at spaces only, so ``imu-gap:START`` stays whole."""

    def _split_lines(self, text: str, width: int) -> list[str]:
        return textwrap.wrap(" ".join(text.split()), width, break_on_hyphens=False, break_long_words=False)


def finish_subcommand(parser: argparse.ArgumentParser) -> None:
    """What every subcommand (and sub-subcommand) shares: the help layout, and -v/-q after the
    subcommand too (``vtolpose replay d -q``; SUPPRESS keeps one given before it)."""
    parser.formatter_class = HelpFormatter
    parser.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS, help="debug logging")
    parser.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help="warnings and errors only")
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for nested in action.choices.values():
                finish_subcommand(nested)


def main(argv: list[str] | None = None) -> int:
    """The program (``argv`` None: the process's own command line) or a command line run by a caller."""
    if argv is None:
        from vtolpose.service.runtime.kernels import compile_in_background

        compile_in_background()  # a user's command does not wait for a cold kernel cache (service/runtime/kernels.py)
        argv = sys.argv[1:]
    first = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser([first] if first is not None else [])
    args = parser.parse_args(argv)
    level = logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return int(args.run(args) or 0)
    except ConfigError as exc:
        print(f"vtolpose {args.command}: configuration error: {exc}", file=sys.stderr)
        return 2
    except (OSError, ValueError) as exc:
        print(f"vtolpose {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"vtolpose {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
