"""Shared fixtures: where the project's shared data lives, and a skip when it is absent."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

# Property tests check what comes out, never how fast: on a loaded machine (CI, other jobs) a draw can
# wait a second for the CPU, which Hypothesis's deadline and "too slow" health check would call a failure.
settings.register_profile("vtolpose", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("vtolpose")

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED = REPO_ROOT.parent / "shared"
EUROC_MH01 = SHARED / "data" / "euroc_mh01"
EUROC_DEV = SHARED / "data" / "euroc_dev"
REALSENSE_HANDHELD = SHARED / "data" / "realsense_handheld"


@pytest.fixture(scope="session")
def euroc_mh01() -> Path:
    """The real EuRoC MH01 folder; tests that need it skip on a clone without ../shared."""
    if not (EUROC_MH01 / "mav0" / "imu0" / "data.csv").is_file():
        pytest.skip(f"needs the shared flight data at {EUROC_MH01} (present in CI, absent in a plain clone)")
    return EUROC_MH01


@pytest.fixture(scope="session")
def realsense_handheld() -> Path:
    """40 s of a real hand-held RealSense recording (JPEG frames, IMU, no truth); skipped without ../shared."""
    if not (REALSENSE_HANDHELD / "mav0" / "cam0" / "data.csv").is_file():
        pytest.skip(f"needs the shared hand-held recording at {REALSENSE_HANDHELD} (present in CI, absent in a plain clone)")
    return REALSENSE_HANDHELD


@pytest.fixture(scope="session")
def euroc_dev() -> Path:
    """The real EuRoC MH03, V101 and V201 folders (IMU and truth.tum); skipped on a clone without ../shared."""
    if not all((EUROC_DEV / name / "mav0" / "imu0" / "data.csv").is_file() for name in ("MH03", "V101", "V201")):
        pytest.skip(f"needs the shared flight data at {EUROC_DEV} (present in CI, absent in a plain clone)")
    return EUROC_DEV


@pytest.fixture(scope="session")
def rendered_book_dir(tmp_path_factory) -> Path:
    """The rendered 24 s book flight (seed 1: 10 s on the spot, then the arm waves the platform), made once
    for every module that replays it (rendering takes seconds); skipped without the 'sim' extra."""
    pytest.importorskip("skimage", reason="rendering needs scikit-image (the 'sim' extra)")
    from vtolpose.drivers.simulator import simulate_flight
    from vtolpose.drivers.simulator.export import write_flight
    from vtolpose.drivers.simulator.render import default_camera

    root = tmp_path_factory.mktemp("book") / "book"
    write_flight(simulate_flight("book", 24.0, 1), root, camera=default_camera())
    return root
