"""Rendered camera frames: geometry consistent with the camera model, determinism, the dataset layout."""

from __future__ import annotations

import itertools
import logging
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("skimage", reason="rendering needs scikit-image (the 'sim' extra)")

from vtolpose.drivers.files.dataset import CAM_CSV, Dataset  # noqa: E402
from vtolpose.drivers.simulator import simulate_flight  # noqa: E402
from vtolpose.drivers.simulator.export import write_flight  # noqa: E402
from vtolpose.drivers.simulator.render import FrameRenderer, RenderOptions, default_camera, render_frames  # noqa: E402
from vtolpose.estimator.vision.camera_model import CameraModel  # noqa: E402


@pytest.fixture(scope="module")
def book(simulated_flight):
    return simulated_flight("book", 16.0, 1)


def first_frames(flight, n: int, **options) -> list[tuple[int, np.ndarray]]:
    return list(itertools.islice(render_frames(flight, options=RenderOptions(**options) if options else None), n))


def test_frames_have_the_camera_size_rate_and_change_with_motion(book):
    frames = first_frames(book, 3)
    cam = default_camera()
    times = [t for t, _ in frames]
    assert np.diff(times).tolist() == [133_333_333, 133_333_334]
    for _, image in frames:
        assert image.shape == (cam.height, cam.width) and image.dtype == np.uint8
        assert 20 < image.mean() < 235 and image.std() > 10  # exposed, textured
    renderer = FrameRenderer(book, cam)
    c_w, R_WC = renderer.pose(np.array([13.0, 13.0 + 1 / 7.5]))  # the arm moves by then
    a, b = (renderer.radiance(c_w[k], R_WC[k])[0] for k in range(2))
    assert np.abs(a - b).mean() > 0.02


def test_same_seed_same_images_other_seed_other_noise(book):
    a = first_frames(book, 2)
    b = first_frames(book, 2)
    c = list(itertools.islice(render_frames(simulate_flight("book", 16.0, 2)), 2))
    for (ta, ia), (tb, ib), (tc, ic) in zip(a, b, c):
        assert ta == tb == tc
        np.testing.assert_array_equal(ia, ib)
        assert not np.array_equal(ia, ic)
        assert np.abs(ia.astype(int) - ic.astype(int)).mean() < 12  # same scene, different noise/exposure


@pytest.mark.parametrize("scenario, t_s", [("book", 13.0), ("landfill", 60.0)])
def test_rendered_pixels_show_the_ground_point_the_camera_model_projects_there(scenario, t_s):
    flight = simulate_flight(scenario, t_s + 1.0, 1)
    cam = default_camera()
    renderer = FrameRenderer(flight, cam)
    c_w, R_WC = (x[0] for x in renderer.pose(np.array([t_s])))
    image, _ = renderer.radiance(c_w, R_WC)
    model = CameraModel(cam)
    rng = np.random.default_rng(0)
    uv = np.column_stack([rng.integers(40, cam.width - 40, 200), rng.integers(40, cam.height - 40, 200)]).astype(float)
    # Cast the exact ray of each pixel: march to the first point under the ground, then bisect.
    rays = model.rays(uv) @ R_WC.T
    ground = flight.scenario.ground_height
    steps = np.linspace(0.01, 3.0 if scenario == "book" else 150.0, 3000)
    under = np.stack([(c_w[2] + t * rays[:, 2]) > ground(c_w[0] + t * rays[:, 0], c_w[1] + t * rays[:, 1]) for t in steps])
    first = np.argmax(under, axis=0)
    assert np.all(under[first, np.arange(len(uv))])
    lo, hi = steps[first - 1], steps[first]
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        pts = c_w + mid[:, None] * rays
        below = pts[:, 2] > ground(pts[:, 0], pts[:, 1])
        hi, lo = np.where(below, mid, hi), np.where(below, lo, mid)
    pts = c_w + hi[:, None] * rays
    footprint = float(np.median(hi)) / cam.fx
    expected = renderer.appearance.radiance(*(pts[:, i].reshape(1, -1).astype(np.float32) for i in range(3)), footprint)[0]
    got = image[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    # The renderer interpolates its geometry between grid rays: nearly all agree (a pixel or a
    # distortion term off would fail most of them); a few may sit on the book's edge.
    close = np.abs(got - expected) < 0.03
    assert close.mean() > 0.95


def test_write_flight_with_camera_keeps_imu_gps_truth_bytes(tmp_path: Path):
    flight = simulate_flight("book", 1.0, 3)
    plain = write_flight(flight, tmp_path / "plain")
    with_cam = write_flight(flight, tmp_path / "cam", camera=default_camera())
    for rel in ("mav0/imu0/data.csv", "mav0/gps0/data.csv", "mav0/state_groundtruth_estimate0/data.csv"):
        assert (plain / rel).read_bytes() == (with_cam / rel).read_bytes()
    ds = Dataset.open(with_cam)
    assert ds.has_camera and not Dataset.open(plain).has_camera
    assert ds.calibration.camera.width == 656 and ds.calibration.camera.rate_hz == 7.5
    np.testing.assert_array_equal(ds.calibration.camera.R_BC, default_camera().R_BC)
    frames = ds.camera_frames()
    assert len(frames) == 7 and all(p.is_file() for _, p in frames)
    expected = next(iter(render_frames(flight)))
    assert frames[0][0] == expected[0]
    np.testing.assert_array_equal(ds.load_frame(frames[0][1]), expected[1])


def test_camera_index_skips_bad_lines_and_counts_missing_images(tmp_path: Path, caplog):
    flight = simulate_flight("book", 0.5, 3)
    root = write_flight(flight, tmp_path / "ds", camera=default_camera())
    index = root / CAM_CSV
    lines = index.read_text().splitlines()
    lines[2:2] = ["not-a-time,x.png", "123", f"{int(lines[1].split(',')[0]) - 5},early.png"]
    lines.append("9999999999999,gone.png")
    index.write_text("\n".join(lines) + "\n")
    ds = Dataset.open(root)
    with caplog.at_level(logging.WARNING):
        frames = ds.camera_frames()
    assert ds.skipped[CAM_CSV] == 3 and "line 3" in caplog.text
    assert [p.name for _, p in frames][-1] == "gone.png"
    with caplog.at_level(logging.WARNING):
        assert ds.load_frame(frames[-1][1]) is None
    assert "gone.png" in caplog.text and ds.skipped["mav0/cam0/data"] == 1
