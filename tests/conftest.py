"""Shared fixtures: where the project's shared data lives, and a skip when it is absent."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED = REPO_ROOT.parent / "shared"
EUROC_MH01 = SHARED / "data" / "euroc_mh01"
EUROC_DEV = SHARED / "data" / "euroc_dev"


@pytest.fixture(scope="session")
def euroc_mh01() -> Path:
    """The real EuRoC MH01 folder; tests that need it skip on a clone without ../shared."""
    if not (EUROC_MH01 / "mav0" / "imu0" / "data.csv").is_file():
        pytest.skip(f"needs the shared flight data at {EUROC_MH01} (present in CI, absent in a plain clone)")
    return EUROC_MH01


@pytest.fixture(scope="session")
def euroc_dev() -> Path:
    """The real EuRoC MH03, V101 and V201 folders (IMU and truth.tum); skipped on a clone without ../shared."""
    if not all((EUROC_DEV / name / "mav0" / "imu0" / "data.csv").is_file() for name in ("MH03", "V101", "V201")):
        pytest.skip(f"needs the shared flight data at {EUROC_DEV} (present in CI, absent in a plain clone)")
    return EUROC_DEV
