"""``vtolpose bench --against REV``: each figure beside the same figure of another commit, measured in the same run.

A speed figure from one machine, one hour, says little on its own: the VM next door, the CPU's clock and the
cache's state move it by tens of percent. Measured against the previous commit in the same run, alternately,
the ratio holds. The other commit is checked out in a temporary git worktree of this source tree and put first
on ``PYTHONPATH`` (its ``vtolpose`` namespace made of links to the worktree's four folders); each round runs the
benchmark once for it and once for this tree, each in a fresh process (so neither inherits the other's warm
caches), the other commit first. A commit's kernels compile on its first round (in no figure: the benchmarks
load their kernels before they time anything). The figure of each side is the median of its rounds.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

from vtolpose.service.bench.rows import Row

PARTS = ("config", "drivers", "estimator", "service")  # the folders the vtolpose namespace is made of
_MARK = "vtolpose-bench-rows "  # the line a benchmark's process gives its rows on

# Run in the process of either side: one benchmark, its rows as JSON on one marked line (whatever else it prints).
_DRIVER = """
import importlib, json, sys
kernels = importlib.import_module("vtolpose.service.runtime.kernels")
if hasattr(kernels, "compile_in_background"):  # the figures are the compiled kernels', as `vtolpose bench` has them
    kernels.compile_in_background(False)
from vtolpose.service.bench.runner import BENCHMARKS
from vtolpose.service.bench.rows import Row
rows = [list(Row(*row)) for row in BENCHMARKS[sys.argv[1]]()]
print(%r + json.dumps(rows), flush=True)
""" % _MARK


class AgainstError(RuntimeError):
    """The other commit cannot be measured here (no git checkout, an unknown commit, a benchmark it lacks)."""


def source_tree() -> Path:
    """The folder this vtolpose runs from (its four parts side by side)."""
    return Path(__file__).resolve().parents[2]


def _git(repo: Path, *args: str) -> str:
    done = subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise AgainstError(f"git {' '.join(args)} in {repo}: {done.stderr.strip() or 'failed'}")
    return done.stdout.strip()


@contextmanager
def other_commit(rev: str, repo: Path | None = None) -> Iterator[tuple[str, Path]]:
    """A worktree of ``rev`` and the folder to put first on ``PYTHONPATH`` for it; both gone afterwards.
    Yields the commit's short hash and that folder."""
    repo = repo or source_tree()
    try:
        top = Path(_git(repo, "rev-parse", "--show-toplevel"))
    except (AgainstError, OSError) as exc:
        raise AgainstError(f"--against needs vtolpose run from a git checkout; {repo} is not one ({exc})") from exc
    try:
        commit = _git(top, "rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}")
    except AgainstError as exc:
        raise AgainstError(f"no commit {rev!r} in {top}") from exc
    short = _git(top, "rev-parse", "--short", commit)
    with tempfile.TemporaryDirectory(prefix="vtolpose-against-") as tmp:
        tree, path = Path(tmp) / "tree", Path(tmp) / "path"
        _git(top, "worktree", "add", "--detach", "--quiet", str(tree), commit)
        try:
            (path / "vtolpose").mkdir(parents=True)
            for part in PARTS:
                (path / "vtolpose" / part).symlink_to(tree / part, target_is_directory=True)
            yield short, path
        finally:
            _git(top, "worktree", "remove", "--force", str(tree))


def rows_of(name: str, pythonpath: Path | None) -> list[Row]:
    """Benchmark ``name`` in a fresh process, of the commit on ``pythonpath`` (None: this tree)."""
    env = dict(os.environ)
    if pythonpath is None:
        env.pop("PYTHONPATH", None)
    else:
        env["PYTHONPATH"] = str(pythonpath)
    done = subprocess.run([sys.executable, "-c", _DRIVER, name], capture_output=True, text=True, env=env)
    marked = [line[len(_MARK):] for line in done.stdout.splitlines() if line.startswith(_MARK)]
    if done.returncode != 0 or not marked:
        tail = "\n".join(done.stderr.strip().splitlines()[-5:])
        raise AgainstError(f"benchmark {name!r} of {'this tree' if pythonpath is None else 'the other commit'} "
                           f"failed (exit {done.returncode}): {tail or 'no figures printed'}")
    return [Row(*row) for row in json.loads(marked[-1])]


def side_by_side(theirs: list[list[Row]], ours: list[list[Row]], short: str) -> list[Row]:
    """Per figure: this tree's median over the rounds (with its target) and, where the other commit has the same
    figure, the other's median and this tree's ÷ the other's."""
    rows = []
    for row in ours[0]:
        mine = statistics.median(r.value for rnd in ours for r in rnd if r.name == row.name)
        other = [r.value for rnd in theirs for r in rnd if r.name == row.name]
        if not other:
            rows.append(row._replace(value=mine, note=f"{short} has no such figure; {row.note}".rstrip("; ")))
            continue
        base = statistics.median(other)
        rows.append(row._replace(value=mine, note=f"{short}: {base:.4g} {row.unit}; {row.note}".rstrip("; ")))
        rows.append(Row(f"  {row.name.strip()}: now / {short}", mine / base if base else float("nan"), "x",
                        f"medians of {len(ours)} round(s) each, alternating, the same run"))
    return rows


def run_against(names: list[str], rev: str, rounds: int, echo: Callable[[str], None] = print,
                repo: Path | None = None) -> list[Row]:
    """Each of ``names`` for ``rev`` and this tree, ``rounds`` times alternately; their figures side by side."""
    if rounds < 1:
        raise AgainstError(f"--rounds must be at least 1, got {rounds}")
    out: list[Row] = []
    with other_commit(rev, repo) as (short, path):
        echo(f"  against {rev} ({short}): a worktree of it first on PYTHONPATH; {rounds} round(s), it first in each")
        for name in names:
            theirs, ours = [], []
            for k in range(rounds):
                theirs.append(rows_of(name, path))
                ours.append(rows_of(name, None))
                echo(f"  ({name}: round {k + 1} of {rounds} done)")
            for row in side_by_side(theirs, ours, short):
                echo(row.line())
                out.append(row)
    return out
