"""``vtolpose bench --against REV``: the other commit really is the one measured (a worktree of it first on the
path), every figure comes with the other's and the ratio, and what cannot be measured says why."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest

from vtolpose.service.bench.against import PARTS, AgainstError, other_commit, rows_of, run_against, source_tree
from vtolpose.service.bench.rows import Row


def _git(repo, *args: str) -> str:
    done = subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


@pytest.fixture(scope="module")
def checkout(tmp_path_factory):
    """A git repository of this tree's four folders, one commit: (the repository, the commit). Made here, so that
    the tests hold wherever vtolpose runs from (a clone, an unpacked copy)."""
    repo = tmp_path_factory.mktemp("checkout")
    for part in PARTS:
        shutil.copytree(source_tree() / part, repo / part, ignore=shutil.ignore_patterns("__pycache__", "*.nbi", "*.nbc"))
    _git(repo, "init", "--quiet")
    _git(repo, "add", ".")
    _git(repo, "-c", "user.name=vtolpose", "-c", "user.email=vtolpose@localhost", "commit", "--quiet", "-m", "tree")
    return repo, _git(repo, "rev-parse", "HEAD")


def test_the_other_commit_is_a_worktree_of_it_first_on_the_path_and_gone_after(checkout):
    repo, commit = checkout
    with other_commit("HEAD", repo) as (short, path):
        tree = (path / "vtolpose" / "estimator").resolve().parent
        assert commit.startswith(short)
        assert _git(tree, "rev-parse", "HEAD") == commit
        for part in ("config", "drivers", "estimator", "service"):
            assert (path / "vtolpose" / part / "__init__.py").is_file()
        found = subprocess.run([sys.executable, "-c", "import vtolpose.estimator as e; print(e.__file__)"],
                               capture_output=True, text=True, env={"PYTHONPATH": str(path), "PATH": ""}).stdout
        assert found.startswith(str(path))  # the other commit's code, not this tree's
    assert str(tree) not in _git(repo, "worktree", "list")
    assert not tree.exists()


def test_each_figure_comes_with_the_other_commits_and_the_ratio(checkout):
    repo, commit = checkout
    lines: list[str] = []
    rows = run_against(["odometry-encoding"], "HEAD", 1, echo=lines.append, repo=repo)
    figures, ratios = rows[0::2], rows[1::2]
    assert len(figures) == len(ratios) >= 4
    for figure, ratio in zip(figures, ratios):
        short, _, rest = figure.note.partition(": ")
        base = float(rest.split()[0])
        assert commit.startswith(short)
        assert ratio.name.endswith(f"now / {short}") and ratio.unit == "x"
        assert ratio.value == pytest.approx(figure.value / base, rel=1e-3)
    assert any("round 1 of 1 done" in line for line in lines)


def test_what_cannot_be_measured_says_why(checkout, tmp_path):
    repo, _ = checkout
    with pytest.raises(AgainstError, match="no commit 'no-such-commit'"):
        run_against(["odometry-encoding"], "no-such-commit", 1, echo=lambda line: None, repo=repo)
    with pytest.raises(AgainstError, match="needs vtolpose run from a git checkout"):
        other_commit("HEAD", repo=tmp_path).__enter__()
    with pytest.raises(AgainstError, match="--rounds must be at least 1"):
        run_against(["odometry-encoding"], "HEAD", 0, echo=lambda line: None, repo=repo)
    done = subprocess.run([sys.executable, "-m", "vtolpose.service.cli", "bench", "--against", "HEAD"],
                          capture_output=True, text=True)
    assert done.returncode == 2 and "--against needs --only" in done.stderr


def test_a_benchmark_runs_in_a_process_of_the_commit_on_the_path(tmp_path):
    """The rows come from the ``vtolpose`` first on the path given (here a stand-in with one benchmark and no
    kernels), not from this tree; a benchmark it lacks is an error that says which side failed."""
    bench = tmp_path / "vtolpose" / "service" / "bench"
    bench.mkdir(parents=True)
    for folder in (tmp_path / "vtolpose" / "service", bench):
        (folder / "__init__.py").write_text("")
    (bench / "rows.py").write_text(
        "from typing import NamedTuple\n"
        "class Row(NamedTuple):\n    name: str\n    value: float\n    unit: str\n    note: str = ''\n"
        "    target: str | None = None\n")
    (bench / "runner.py").write_text("BENCHMARKS = {'stand-in': lambda: [('a figure', 42.0, 'x', 'its note')]}\n")
    (tmp_path / "vtolpose" / "service" / "runtime").mkdir()
    (tmp_path / "vtolpose" / "service" / "runtime" / "__init__.py").write_text("")
    (tmp_path / "vtolpose" / "service" / "runtime" / "kernels.py").write_text("")  # a commit without the option
    assert rows_of("stand-in", tmp_path) == [Row("a figure", 42.0, "x", "its note")]
    with pytest.raises(AgainstError, match="'odometry-encoding' of the other commit failed"):
        rows_of("odometry-encoding", tmp_path)
