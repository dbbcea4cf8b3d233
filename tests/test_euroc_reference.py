"""The GTSAM speed reference of ``vtolpose bench --only euroc-reference``.

gtsam is an optional benchmark extra: without it the bench says so and still measures
vtolpose; with it the reference must really track the flight, or its speed would mean nothing.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.service.bench.euroc import scored_gps_rmse, scored_position_rmse
from vtolpose.service.bench.euroc_reference import bench_euroc_reference, reference_run, sensor_white_noise


def test_without_gtsam_the_reference_is_a_skip_line_not_an_error(monkeypatch, tmp_path: Path) -> None:
    monkeypatch.setitem(sys.modules, "gtsam", None)  # import gtsam then raises ImportError
    monkeypatch.setenv("VTOLPOSE_EUROC_DATA", str(tmp_path))  # no flights either: nothing long to run
    lines: list[str] = []
    assert bench_euroc_reference(lines.append) == []
    assert any("gtsam is not installed" in line and "vtolpose[bench]" in line for line in lines)
    assert any("no EuRoC flight" in line for line in lines)


def test_the_reference_tracks_a_simulated_flight_from_its_imu_and_gps(tmp_path: Path) -> None:
    gtsam = pytest.importorskip("gtsam", reason="the optional bench extra (gtsam) is not installed")
    write_flight(simulate_flight("book", 30.0, 1), tmp_path / "book")
    dataset = Dataset.open(tmp_path / "book")
    result = reference_run(gtsam, dataset)
    gps = dataset.gps()
    assert result["wall_s"] > 0.0 and result["duration_s"] == pytest.approx(30.0, abs=0.1)
    # Within the GPS's own scatter: a reference that lost the IMU or the GPS would be metres off.
    assert result["rmse_m"] < 2.0 * float(np.max(gps.sigma_h)) + 0.05


def test_the_references_causal_trajectory_is_each_fixs_state_carried_to_every_imu_sample(tmp_path: Path) -> None:
    """Scored as vtolpose is, the reference must publish between fixes too: from each fix on, a pose at every IMU
    sample up to the next fix, made from what it knew at that fix; at the fix itself its newest state."""
    gtsam = pytest.importorskip("gtsam", reason="the optional bench extra (gtsam) is not installed")
    write_flight(simulate_flight("book", 20.0, 2), tmp_path / "book")
    dataset = Dataset.open(tmp_path / "book")
    result = reference_run(gtsam, dataset, causal=True)
    trajectory, imu, gps = result["trajectory"], dataset.imu(), dataset.gps()
    first_fix = int(gps.t_ns[gps.t_ns >= imu.t_ns[0]][0])
    assert np.all(np.diff(trajectory.t_ns) > 0) and trajectory.t_ns[0] == first_fix
    later = imu.t_ns[imu.t_ns > first_fix]
    assert set(later.tolist()) <= set(trajectory.t_ns.tolist())  # every IMU sample after the first fix has a pose
    assert set(gps.t_ns[gps.t_ns >= first_fix].tolist()) <= set(trajectory.t_ns.tolist())  # and every fix
    np.testing.assert_allclose(np.linalg.norm(trajectory.q, axis=1), 1.0, atol=1e-9)
    gps_rmse = scored_gps_rmse(dataset)
    between = scored_position_rmse(trajectory, dataset)
    # The poses between fixes are predictions: worse than the updates alone, yet within the GPS's own error.
    assert 0.0 < between < gps_rmse and between > 0.5 * result["rmse_m"]


def test_the_imus_datasheet_noise_is_read_from_the_recordings_sensor_yaml(tmp_path: Path) -> None:
    """EuRoC's ``sensor.yaml`` has OpenCV's ``%YAML:1.0`` header line; a recording without one, or one without the
    densities, has no datasheet figures (the bench then runs the reference once, with the vehicle file's)."""
    imu0 = tmp_path / "mav0" / "imu0"
    imu0.mkdir(parents=True)
    assert sensor_white_noise(tmp_path) is None
    (imu0 / "sensor.yaml").write_text("%YAML:1.0\nsensor_type: imu\nrate_hz: 200\n"
                                      "gyroscope_noise_density: 1.6968e-04\naccelerometer_noise_density: 2.0000e-3\n")
    assert sensor_white_noise(tmp_path) == (1.6968e-04, 2.0e-3)
    (imu0 / "sensor.yaml").write_text("%YAML:1.0\nsensor_type: imu\n")
    assert sensor_white_noise(tmp_path) is None


def test_each_side_counts_its_best_run_of_the_rounds_taken_in_turn(monkeypatch) -> None:
    """A replay is deterministic, so its runs differ only by what the machine was doing: the bench runs both
    sides in turn and counts each one's fastest run (the median said beside it), so that a slow minute
    neither flatters nor spoils the ratio."""
    from types import SimpleNamespace

    from vtolpose.service.bench import euroc_reference as bench

    walls = {"biases": iter([2.0, 0.5, 1.0]), "thesis": iter([0.4, 0.8, 0.6])}
    reference_walls = iter([4.0, 1.0, 2.0])
    order: list[str] = []

    def replay(dataset, cfg, sensors):
        variant = cfg["estimator.variant"]
        order.append(variant)
        return SimpleNamespace(wall_s=next(walls[variant]), duration_s=100.0, trajectory=None)

    def reference_run(gtsam, dataset, causal=False):
        order.append("reference")
        wall = next(reference_walls)
        return {"wall_s": wall, "cpu_s": wall, "duration_s": 100.0, "rmse_m": 0.02}

    monkeypatch.setattr(bench, "replay", replay)
    monkeypatch.setattr(bench, "reference_run", reference_run)
    monkeypatch.setattr(bench, "flights_or_skip", lambda name, echo: [SimpleNamespace(name="F")])
    monkeypatch.setattr(bench, "imported_flight", lambda flight, work: SimpleNamespace(truth=lambda: None))
    monkeypatch.setattr(bench, "load_compiled_kernels", lambda: None)
    monkeypatch.setitem(sys.modules, "gtsam", SimpleNamespace())
    rows = {row.name: row for row in bench.bench_euroc_reference(lambda line: None)}
    assert order == ["biases", "thesis", "reference"] * 3
    assert rows["F replay imu,gps (biases)"].value == pytest.approx(200.0)  # 100 s / 0.5 s
    assert "median 100 x" in rows["F replay imu,gps (biases)"].note
    assert rows["F replay imu,gps (thesis)"].value == pytest.approx(250.0)
    assert rows["F GTSAM reference"].value == pytest.approx(100.0)
    assert rows["F vtolpose / reference (biases)"].value == pytest.approx(2.0)
    assert rows["F vtolpose / reference (thesis)"].value == pytest.approx(2.5)
