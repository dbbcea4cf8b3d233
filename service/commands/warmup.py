"""``vtolpose warmup``: the estimator's kernels compiled into numba's cache, once per machine."""

from __future__ import annotations

import argparse
import os


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "warmup",
        help="compile the estimator's kernels once (about half a minute), so no run waits for them",
        description="Compile the estimator's numba kernels into their cache (beside the sources when writable, else\n"
        "~/.cache/vtolpose/numba, or NUMBA_CACHE_DIR), or load them when they are there already. A Docker image\n"
        "runs it at build time. Without it, the first replay or daemon start runs the kernels interpreted (the same\n"
        "results, slower) and starts this command in the background once it has run 10 s, or as it ends; a second\n"
        "compiler waits for the first.\n\n"
        "Examples:\n"
        "  vtolpose warmup\n"
        "  NUMBA_CACHE_DIR=/var/cache/vtolpose-numba vtolpose warmup",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--nice", action="store_true", help="at low CPU priority (as a command starts it in the background)")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if args.nice and hasattr(os, "nice"):
        os.nice(10)
    from vtolpose.service.runtime.kernels import cache_place, compile_lock, load_compiled_kernels

    with compile_lock():
        load = load_compiled_kernels(backward_pass=True, runs=True, wait=True)
    if load.compile_s is not None:
        print(f"compiled the estimator's kernels, once ({load.compile_s:.1f} s), into {cache_place()}")
    else:
        print(f"the estimator's kernels are compiled already: loaded in {load.load_s:.2f} s from {cache_place()}")
    return 0
