"""Shared fixtures: where the project's shared data lives (and a skip when it is absent), simulated flights
made once per session for every module that flies the same one, and a free loopback port."""

from __future__ import annotations

import socket
from pathlib import Path
from typing import Any, Callable

import numpy as np
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


def central_difference(f: Callable[[np.ndarray], np.ndarray], x: np.ndarray, h: float) -> np.ndarray:
    """The Jacobian of ``f`` at ``x`` by central differences of step ``h`` (a column per component of ``x``)."""
    cols = []
    for i in range(x.shape[-1]):
        d = np.zeros(x.shape[-1])
        d[i] = h
        cols.append((f(x + d) - f(x - d)) / (2 * h))
    return np.stack(cols, axis=-1)


def check_projection_jacobian(cam, P: np.ndarray) -> None:
    """A camera model's ``project_jacobian`` against central differences of ``project`` at the points ``P``."""
    uv, _, J = cam.project_jacobian(P)
    for i in range(len(P)):
        numeric = central_difference(lambda x: cam.project(x[None])[0][0], P[i], 1e-6 * P[i, 2])
        np.testing.assert_allclose(J[i], numeric, rtol=1e-5, atol=1e-6 * np.abs(J[i]).max())
    np.testing.assert_allclose(uv, cam.project(P)[0])


def check_lens_jacobians(cam, xn: np.ndarray, undistort_rtol: float = 1e-7) -> None:
    """A camera model's distortion Jacobian at ``xn`` and its undistortion Jacobian (d x / d uv) at their pixels,
    each against central differences of the function itself."""
    D = cam.distort_jacobian(xn)
    for i in range(len(xn)):
        np.testing.assert_allclose(D[i], central_difference(lambda x: cam.distort(x), xn[i], 1e-7), atol=1e-7)
    uv = cam.normalized_to_pixel(xn)
    U = cam.undistort_jacobian(xn)
    for i in range(len(xn)):
        np.testing.assert_allclose(U[i], central_difference(lambda p: cam.undistort(p[None])[0], uv[i], 1e-3),
                                   rtol=undistort_rtol, atol=1e-9)


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A loopback port nothing listens on now (TCP, or UDP with ``socket.SOCK_DGRAM``), for a real peer."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def pose_client_when_listening(port: int, timeout_s: float = 10.0, prefix: str = "vtolpose/vtol1"):
    """A PoseClient connected to a service on loopback ``port`` once it listens (it opens its outputs after
    loading its data); AssertionError if it never does within ``timeout_s``."""
    import time

    from vtolpose.service.outputs.pose_client import PoseClient

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            return PoseClient(prefix, connect=[f"tcp/127.0.0.1:{port}"], timeout_s=5.0)
        except Exception:  # zenoh.ZError: nobody listening yet
            time.sleep(0.1)
    raise AssertionError("the service never listened")


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


# Tests that time real peers on loopback (Zenoh sessions, serial pseudo-terminals, a live map against a paced
# replay, poses leaving while a paced flight's update is held) against wall-clock deadlines: on a loaded 2-core machine one of them now and then misses its deadline
# (a Zenoh sample dropped under congestion, a packet read late) and passes when run again. They run once more
# before failing, where pytest-rerunfailures is installed (the `test` extra); a broken behaviour fails both runs.
WALL_CLOCK_TESTS = {
    "test_crossbow.py::test_corrupted_stream_and_a_reboot_lose_only_the_damaged_packets",
    "test_crossbow.py::test_stream_resumes_after_the_cable_is_pulled_mid_stream",
    "test_fusion_thread.py::test_a_slow_frame_update_on_the_fusion_thread_leaves_every_pose_going_and_fuses_as_the_loop_alone",
    "test_map_zenoh.py::test_live_map_over_zenoh_equals_the_map_from_the_trajectory_file",
    "test_map_zenoh.py::test_live_map_of_smoothed_poses_equals_the_map_from_the_fixed_lag_trajectory",
    "test_pose_client.py::test_the_client_believes_only_the_service_session",
    "test_runtime.py::test_camera_work_does_not_hold_up_poses_and_is_fused_at_the_frame_time",
    "test_runtime.py::test_the_bare_sends_of_the_latency_bench_reach_their_peers",
    "test_zenoh_pose_json.py::test_the_published_bytes_and_sequence_numbers_on_loopback",
}


def pytest_collection_modifyitems(config, items):
    if not config.pluginmanager.hasplugin("rerunfailures"):
        return
    for item in items:
        if f"{item.path.name}::{item.originalname}" in WALL_CLOCK_TESTS:
            item.add_marker(pytest.mark.flaky(reruns=1, reruns_delay=1))
