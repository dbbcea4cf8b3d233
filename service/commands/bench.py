"""``vtolpose bench``: speed figures on this machine."""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

from vtolpose.service.bench.catalog import LONG_BENCHMARKS, SUMMARIES


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench",
        help="speed figures on this machine (can it keep up?)",
        description="Measure what the estimator costs on this computer and print the figures:\n"
        + "\n".join(f"  {name:<15} {summary}" for name, summary in SUMMARIES.items())
        + f"\n\nWithout --only every benchmark runs except the long ones ({', '.join(LONG_BENCHMARKS)}; "
        "minutes to a quarter of an hour each): name them with --only, or pass --all.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--only", action="append", choices=sorted(SUMMARIES), help="run only these (repeatable)")
    p.add_argument("--all", action="store_true", help="also run the long benchmarks")
    p.add_argument("--against", metavar="REV",
                   help="each figure beside the same figure of git commit REV (e.g. HEAD~1), measured in the same "
                        "run, alternately, each side in a process of its own (needs a git checkout; with --only)")
    p.add_argument("--rounds", type=int, default=3, metavar="N",
                   help="with --against: runs of each side, alternating; each figure is their median (default 3)")
    p.set_defaults(run=run)


def cpu_model() -> str:
    """The CPU's model name (Linux /proc/cpuinfo), else what the platform module knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:  # not Linux, or /proc not mounted: the platform module's answer below
        pass
    return platform.processor() or platform.machine()


def machine_line() -> str:
    """Which machine the figures belong to: absolute figures do not carry over to another."""
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"vtolpose bench on {platform.node()}: {cpu_model()}, {os.cpu_count()} cores, Python "
            f"{platform.python_version()}, load average {load:.2f} at the start")


def run(args: argparse.Namespace) -> int:
    from vtolpose.service.runtime.kernels import compile_in_background

    compile_in_background(False)  # the figures are the compiled kernels'; compiling them is before any clock starts
    from vtolpose.service.bench.runner import run_benchmarks

    print(machine_line())
    if args.against is not None:
        from vtolpose.service.bench.against import AgainstError, run_against

        if not args.only:
            print("vtolpose bench: --against needs --only (each benchmark runs 2 x --rounds times)", file=sys.stderr)
            return 2
        try:
            run_against(args.only, args.against, args.rounds)
        except AgainstError as exc:
            print(f"vtolpose bench: {exc}", file=sys.stderr)
            return 2
        return 0
    run_benchmarks(args.only, include_long=args.all)
    return 0
