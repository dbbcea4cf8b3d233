"""End to end: a short rendered book flight through replay — the camera must add information.

Test 3 (imu,camera,gps) must beat Test 1 (imu,gps) on the same data, Test 2 (imu,camera) must
keep its drift bounded without any absolute position. ORB keeps this test fast; SIFT (the
default) is exercised in the benchmarks and the per-module tests.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

pytest.importorskip("skimage", reason="rendering needs scikit-image (the 'sim' extra)")

from vtolpose.config import load_config  # noqa: E402
from vtolpose.drivers.files.dataset import Dataset  # noqa: E402
from vtolpose.drivers.simulator import simulate_flight  # noqa: E402
from vtolpose.drivers.simulator.export import write_flight  # noqa: E402
from vtolpose.drivers.simulator.render import default_camera  # noqa: E402
from vtolpose.service.replay.overlay import OverlayWriter  # noqa: E402
from vtolpose.service.replay.session import replay  # noqa: E402
from vtolpose.service.replay.report import build_report, summary_lines  # noqa: E402

DURATION_S = 24.0  # the shared rendered book flight: 10 s on the spot, then the arm starts to wave the platform
CLIP_S = 3.0  # the overlay's clip


@pytest.fixture(scope="module")
def book(rendered_book_dir) -> Dataset:
    return Dataset.open(rendered_book_dir)  # the 24 s rendered book flight (conftest.py)


def run(dataset: Dataset, sensors: list[str], variant: str = "biases", **kwargs) -> dict:
    cfg = load_config(None, {"estimator": {"variant": variant}, "features": {"detector": "orb"}})
    result = replay(dataset, cfg, sensors, **kwargs)
    report = build_report(result, dataset, cfg)
    assert result.estimator.state.is_finite()
    summary_lines(report)  # the console summary must cope with camera runs
    return report


def test_camera_with_gps_beats_gps_alone(book: Dataset):
    test1 = run(book, ["imu", "gps"])
    test3 = run(book, ["imu", "camera", "gps"])
    assert test3["position_rmse_m"] < 0.7 * test1["position_rmse_m"]
    assert test3["attitude_rmse_deg"] < 1.0
    assert test3["nees"]["mean_in_band"]
    cam = test3["camera"]
    assert cam["frames"] == int(DURATION_S * 7.5) and cam["frames_used"] >= cam["frames"] - 20  # before start
    assert cam["matches_per_frame"]["mean"] > 8 and cam["landmarks_initialised"] > 30
    assert cam["depth_prior_sources"].get("height", 0) > 0  # GPS gives the height above the table
    assert test3["sensors"]["camera_match"]["used"] > 500


def test_camera_without_gps_keeps_drift_bounded(book: Dataset):
    test2 = run(book, ["imu", "camera"])
    assert test2["position_reference"]["kind"] == "start"
    assert test2["drift_percent"] < 2.0 and test2["position_rmse_m"] < 0.03  # the Test 2 target: drift <= 2 %
    assert test2["attitude_rmse_deg"] < 1.0
    imu_only = run(book, ["imu"])
    assert test2["final_drift_m"] < 0.5 * imu_only["final_drift_m"]


def test_a_camera_replay_overlays_every_frame(tmp_path: Path):
    """The overlay on a short rendered clip (3 s, 22 frames): one image per frame, camera only."""
    root = write_flight(simulate_flight("book", CLIP_S, 1), tmp_path / "clip", camera=default_camera())
    overlay = OverlayWriter(tmp_path / "overlay")
    run(Dataset.open(root), ["imu", "camera"], on_frame=overlay)
    frames = len(Dataset.open(root).camera_frames())
    assert frames >= int(CLIP_S * 7.5) - 1 and overlay.written == frames
    assert len(list((tmp_path / "overlay").glob("*.jpg"))) == overlay.written


def test_thesis_variant_runs_test_3(book: Dataset):
    test1 = run(book, ["imu", "gps"], "thesis")
    test3 = run(book, ["imu", "camera", "gps"], "thesis")
    assert test3["position_rmse_m"] < 0.7 * test1["position_rmse_m"]
    assert test3["nees"]["mean_in_band"], test3["nees"]  # the thesis model is consistent on this flight too (docs: 8.21)


def test_camera_requested_but_absent_is_a_note_not_an_error(tmp_path: Path):
    root = write_flight(simulate_flight("book", 12.0, 2), tmp_path / "nocam")
    cfg = load_config()
    result = replay(Dataset.open(root), cfg, ["imu", "camera", "gps"])
    assert any("camera" in note for note in result.notes)
    assert result.frames == [] and "camera" not in result.estimator.counts
    assert "camera" not in build_report(result, Dataset.open(root), cfg)


def test_parallel_frame_extraction_gives_the_same_replay(book: Dataset):
    """A full-speed replay extracts several frames at once (replay.camera_workers, two per core by
    default); lock-step fuses them in time order, so the trajectory is the one a single worker gives."""
    import numpy as np
    from vtolpose.config.sections import build_sections
    from vtolpose.service.runtime.daemon import replay_camera_workers

    trajectories = {}
    for workers in (1, 3):
        cfg = load_config(None, {"features": {"detector": "orb"}, "replay": {"camera_workers": workers}})
        assert replay_camera_workers(build_sections(cfg).replay) == workers
        result = replay(book, cfg, ["imu", "camera", "gps"])
        trajectories[workers] = result.trajectory
        assert len(result.frames) == int(DURATION_S * 7.5)
    one, three = trajectories[1], trajectories[3]
    assert np.array_equal(one.t_ns, three.t_ns)
    assert np.array_equal(one.p, three.p) and np.array_equal(one.q, three.q)
    assert replay_camera_workers(build_sections(load_config(None, {})).replay) == min(2 * (os.cpu_count() or 1), 16)  # two per core
