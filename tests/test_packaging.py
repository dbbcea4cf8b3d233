"""The installed form: one top-level name (``vtolpose``), whatever else shares site-packages.

A wheel built from a clean copy of the repository goes into a fresh virtual environment; the
third-party dependencies come from the test's own environment through a plain path entry, so
nothing is downloaded and the wheel's own files are the only vtolpose on the path.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import sysconfig
import textwrap
import venv
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _clean_copy(dst: Path) -> Path:
    """The tracked files only (no build/, no .venv, no egg-info), as a fresh clone has them."""
    try:
        listed = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout
        files = [f for f in listed.decode().split("\0") if f]
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("the packaging test copies the tracked files and needs git and a checkout")
    for rel in files:
        if (REPO / rel).is_file():
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / rel, dst / rel)
    return dst


def _wheel(src: Path, out: Path) -> Path:
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                    "-w", str(out), str(src)], check=True, capture_output=True)
    (wheel,) = out.glob("*.whl")
    return wheel


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """A fresh venv with the vtolpose wheel installed; returns (python, site-packages, names before)."""
    tmp = tmp_path_factory.mktemp("pkg")
    wheel = _wheel(_clean_copy(tmp / "src"), tmp / "dist")
    env = tmp / "venv"
    venv.EnvBuilder(with_pip=True).create(env)
    python = env / "bin" / "python"
    site = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True).stdout.strip())
    before = {p.name for p in site.iterdir()}
    subprocess.run([str(python), "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)],
                   check=True, capture_output=True)
    added = {p.name for p in site.iterdir()} - before
    # The dependencies (numpy, OpenCV, zenoh, …) from this environment, after the venv's own path.
    (site / "zz_test_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return python, site, added, tmp


def test_the_wheel_installs_one_top_level_name(installed):
    _, site, added, _ = installed
    assert {name for name in added if not name.endswith(".dist-info")} == {"vtolpose"}
    assert [name for name in added if name.endswith(".dist-info")] == ["vtolpose-0.1.0.dist-info"]
    assert sorted(p.name for p in (site / "vtolpose").iterdir() if p.is_dir() and p.name != "__pycache__") == [
        "config", "drivers", "estimator", "service"]
    assert (site / "vtolpose" / "config" / "default.yaml").is_file()
    assert (site / "vtolpose" / "config" / "euroc_vi_sensor.yaml").is_file()


def test_a_foreign_config_package_leaves_vtolpose_working(installed):
    python, site, _, tmp = installed
    foreign = tmp / "foreign"
    (foreign / "config").mkdir(parents=True)
    (foreign / "config" / "__init__.py").write_text("def load_config():\n    return 'not vtolpose'\n")
    (foreign / "pyproject.toml").write_text(textwrap.dedent("""\
        [build-system]
        requires = ["setuptools>=64"]
        build-backend = "setuptools.build_meta"
        [project]
        name = "config"
        version = "0.5.1"
        [tool.setuptools]
        packages = ["config"]
        """))
    subprocess.run([str(python), "-m", "pip", "install", "-q", "--no-deps", "--no-index",
                    str(_wheel(foreign, tmp / "foreign-dist"))], check=True, capture_output=True)
    assert (site / "config" / "__init__.py").is_file()
    assert not (site / "config" / "default.yaml").exists()  # nothing of ours mixed into it
    run = tmp / "run"
    run.mkdir()
    demo = subprocess.run([str(python), "-m", "vtolpose", "demo", "--duration", "10"], cwd=run,
                          capture_output=True, text=True, timeout=300)
    assert demo.returncode == 0, demo.stderr[-2000:]
    assert "position RMSE" in demo.stdout
    script = subprocess.run([str(python.parent / "vtolpose"), "--help"], cwd=run, capture_output=True, text=True)
    assert script.returncode == 0 and "vtolpose demo" in script.stdout
    # A mapper with its own config module imports the client without OpenCV.
    (run / "config.py").write_text("MAPPER = True\n")
    client = subprocess.run([str(python), "-c", textwrap.dedent("""\
        import sys, config
        from vtolpose.client import PoseClient, PoseUnavailable
        assert config.MAPPER
        assert "cv2" not in sys.modules, "the client must not need OpenCV"
        print("ok")
        """)], cwd=run, capture_output=True, text=True)
    assert client.stdout.strip() == "ok", client.stderr[-2000:]
