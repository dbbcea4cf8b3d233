"""The camera test matrix's pieces: motion profiles, starts, the floor's real-photo textures, its cameras,
and the bench's registration and verdict (the bench itself is long: ``vtolpose bench --only camera-matrix``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vtolpose.drivers.simulator import ImuErrorModel, SimulationOptions, simulate_flight
from vtolpose.drivers.simulator.cameras import LENSES, matrix_camera
from vtolpose.drivers.simulator.floor import STARTS, FloorScenario, start_options
from vtolpose.drivers.simulator.imu_model import corrupt_imu
from vtolpose.drivers.simulator.motion_profiles import PROFILES
from vtolpose.drivers.simulator.photo_mosaic import PhotoSource, photo_mosaic, shared_photo_sources
from vtolpose.service.bench import camera_matrix
from vtolpose.service.bench.runner import BENCHMARKS, LONG_BENCHMARKS

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def moving_kinematics(profile: str):
    scenario = FloorScenario(profile=PROFILES[profile])
    return scenario.trajectory(60.0, 9.81).kinematics(np.arange(5.0, 65.0, 0.005))


@pytest.mark.parametrize("profile, low, high", [("hover", 0.0, 0.05), ("gentle", 0.10, 0.15), ("aggressive", 1.7, 2.3)])
def test_each_profile_accelerates_within_its_band(profile, low, high):
    k = moving_kinematics(profile)
    rms = float(np.sqrt(np.mean(np.sum(k.a**2, axis=1))))
    assert low <= rms <= high


@pytest.mark.parametrize("profile, low, high", [("hover", 0.0, 0.05), ("gentle", 0.05, 0.25), ("aggressive", 0.85, 1.25)])
def test_each_profile_turns_within_its_band(profile, low, high):
    peak = float(np.max(np.linalg.norm(moving_kinematics(profile).omega_b(), axis=1)))
    assert low <= peak <= high


def test_hover_vibration_shakes_the_imu_not_the_truth():
    model = PROFILES["hover"].imu_model(ImuErrorModel.perfect())
    n = 12_500
    readings = corrupt_imu(np.zeros((n, 3)), np.zeros((n, 3)), model, np.random.default_rng(0))
    np.testing.assert_allclose(np.sqrt(np.mean(readings.accel**2, axis=0)), 0.6, rtol=0.05)
    np.testing.assert_allclose(np.sqrt(np.mean(readings.gyro**2, axis=0)), 0.03, rtol=0.05)
    assert PROFILES["gentle"].imu_model() == ImuErrorModel()  # the others carry none
    with pytest.raises(ValueError, match="vibration_hz"):
        ImuErrorModel(vibration_accel_rms=0.5)


def fly(start: str, duration_s: float = 4.0):
    scenario = FloorScenario()
    return simulate_flight(scenario, duration_s, 1, SimulationOptions(imu=ImuErrorModel.perfect(), **start_options(start, scenario)))


def test_a_start_at_rest_holds_still_for_a_second_then_moves():
    truth = fly("rest").truth
    t = (truth.t_ns - truth.t_ns[0]) * 1e-9
    speed = np.linalg.norm(truth.v, axis=1)
    assert speed[t < 1.0].max() < 1e-9
    assert speed[t > 2.5].min() > 0.01


def test_a_start_in_motion_moves_from_the_first_sample_with_a_stated_heading():
    flight = fly("motion")
    assert np.linalg.norm(flight.truth.v[0]) > 0.05
    assert flight.calibration.initial_heading_rad is not None


def test_a_start_mid_flight_joins_the_trajectory_without_a_stated_heading():
    flight = fly("mid-flight")
    assert flight.calibration.initial_heading_rad is None
    assert np.linalg.norm(flight.truth.v[0]) > 0.05
    with pytest.raises(ValueError, match="unknown start"):
        start_options("airborne", FloorScenario())


def test_the_floor_lies_about_the_height_below_the_camera():
    scenario = FloorScenario()
    n, e = np.meshgrid(np.linspace(-2, 2, 50), np.linspace(-2, 2, 50))
    floor = scenario.ground_height(n, e)
    assert np.abs(floor).max() <= 1.5 * scenario.undulation_m
    assert 0.9 <= -scenario.trajectory(10.0, 9.81).kinematics(np.array([5.0])).p[0, 2] <= 1.5


def test_missing_photos_say_why(tmp_path):
    source = PhotoSource("nowhere", tmp_path / "absent", "*.png")
    assert "no folder" in source.missing()
    with pytest.raises(FileNotFoundError, match="nowhere"):
        photo_mosaic(source)


@pytest.mark.parametrize("texture, frame_shape", [("v101", (480, 752)), ("handheld", (360, 640))])
def test_real_photo_mosaic_loads_the_shared_frames(texture, frame_shape):
    source = shared_photo_sources(SHARED_DATA)[texture]
    if source.missing():
        pytest.skip(f"needs the shared recordings for the texture (present in CI, absent in a plain clone): "
                    f"{source.missing()}")
    mosaic = photo_mosaic(source)
    rows, cols = source.tiles
    assert mosaic.shape == (rows * frame_shape[0], cols * frame_shape[1]) and mosaic.dtype == np.float32
    tile = mosaic[: frame_shape[0], : frame_shape[1]]
    assert abs(float(tile.mean())) < 1e-3 and abs(float(tile.std()) - 1.0) < 1e-3


@pytest.mark.parametrize("lens", LENSES)
def test_each_lens_renders_the_floor(lens):
    pytest.importorskip("skimage", reason="rendering needs scikit-image (the 'sim' extra)")
    from vtolpose.drivers.simulator.render import FrameRenderer

    camera = matrix_camera(lens, 640, 360, 15.0)
    assert camera.model == ("equidistant" if lens == "equidistant" else "radtan")
    renderer = FrameRenderer(fly("motion", 1.0), camera)
    c_w, R_WC = (x[0] for x in renderer.pose(np.array([0.5])))
    image, centre = renderer.radiance(c_w, R_WC)
    assert image.shape == (360, 640) and image.std() > 0.05
    assert abs(centre[2]) < 0.1  # the view's centre is on the floor


def test_the_bench_is_registered_long_and_covers_every_factor():
    assert BENCHMARKS["camera-matrix"] is camera_matrix.bench_camera_matrix and "camera-matrix" in LONG_BENCHMARKS
    cells = camera_matrix.CELLS
    assert {c.profile for c in cells} == set(PROFILES)
    assert {c.lens for c in cells} == set(LENSES)
    assert {c.start for c in cells} == set(STARTS)
    assert {(c.width, c.height) for c in cells} == {(640, 360), (656, 494), (1280, 720)}
    assert {10.0, 20.0} <= {c.rate_hz for c in cells}
    assert {c.texture for c in cells} == {"v101", "handheld", camera_matrix.SAMPLES_TEXTURE}


def score(position: float, attitude: float, in_band: bool = True, resets: int = 0) -> camera_matrix.TestScore:
    return camera_matrix.TestScore(position, attitude, 3.0 if in_band else 30.0, 0.9, in_band, resets)


def test_the_verdict_names_every_failed_condition():
    good = {"Test 1": score(0.02, 0.5), "Test 2": score(0.05, 0.8), "Test 3": score(0.015, 0.4)}
    assert camera_matrix.verdict(good) == []
    bad = {"Test 1": score(0.02, 0.5), "Test 2": score(0.05, 0.8, in_band=False), "Test 3": score(0.03, 0.4, resets=1)}
    assert camera_matrix.verdict(bad) == ["Test 3 position > Test 1", "Test 2 NEES out of band", "Test 3 reset ×1"]


def test_the_bench_skips_cells_whose_photos_are_missing(tmp_path, monkeypatch):
    monkeypatch.setattr(camera_matrix, "photo_root", lambda: tmp_path)
    lines: list[str] = []
    assert camera_matrix.bench_camera_matrix((camera_matrix.BASE,), echo=lines.append) == []
    assert "skipped" in lines[0] and "no folder" in lines[0]
    assert lines[-1].startswith("  | base |") and "skipped" in lines[-1]
