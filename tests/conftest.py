"""Shared fixtures: where the project's shared data lives (and a skip when it is absent), simulated flights
made once per session for every module that flies the same one, and a free loopback port."""

from __future__ import annotations

import socket
from pathlib import Path
from typing import Any, Callable

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


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A loopback port nothing listens on now (TCP, or UDP with ``socket.SOCK_DGRAM``), for a real peer."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="session")
def simulated_flight() -> Callable[..., Any]:
    """``simulate_flight(scenario, duration_s, seed, options)``, flown once per session for each set of
    arguments (the same arguments give the same arrays, so the modules that fly the same flight share it).
    The flights are shared: a test must not change their arrays."""
    from vtolpose.drivers.simulator import simulate_flight

    flown: dict[tuple, Any] = {}

    def fly(scenario: str, duration_s: float, seed: int, options: Any = None) -> Any:
        key = (scenario, float(duration_s), int(seed), repr(options))
        if key not in flown:
            flown[key] = simulate_flight(scenario, duration_s, seed, options)
        return flown[key]

    return fly


@pytest.fixture(scope="session")
def flight_folder(tmp_path_factory, simulated_flight) -> Callable[..., Path]:
    """A simulated flight written in the dataset layout (``camera``: with rendered frames, which takes seconds
    and needs the 'sim' extra, else skipped), once per session for each set of arguments."""
    written: dict[tuple, Path] = {}

    def folder(scenario: str, duration_s: float, seed: int, options: Any = None, camera: bool = False) -> Path:
        key = (scenario, float(duration_s), int(seed), repr(options), camera)
        if key not in written:
            from vtolpose.drivers.simulator.export import write_flight

            frames = None
            if camera:
                pytest.importorskip("skimage", reason="rendering needs scikit-image (the 'sim' extra)")
                from vtolpose.drivers.simulator.render import default_camera

                frames = default_camera()
            root = tmp_path_factory.mktemp(scenario) / scenario
            write_flight(simulated_flight(scenario, duration_s, seed, options), root, camera=frames)
            written[key] = root
        return written[key]

    return folder


@pytest.fixture(scope="session")
def book(simulated_flight) -> Any:
    """The 45 s book flight of seed 3 (10 s on the spot, then the arm waves; its heading found in motion)."""
    return simulated_flight("book", 45.0, 3)


@pytest.fixture(scope="session")
def rendered_book_dir(flight_folder) -> Path:
    """The rendered 24 s book flight (seed 1: 10 s on the spot, then the arm waves the platform), made once
    for every module that replays it (rendering takes seconds); skipped without the 'sim' extra."""
    return flight_folder("book", 24.0, 1, camera=True)
