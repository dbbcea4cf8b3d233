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
from vtolpose.service.bench.euroc_reference import bench_euroc_reference, reference_run


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
        return SimpleNamespace(wall_s=next(walls[variant]), duration_s=100.0)

    def reference_run(gtsam, dataset):
        order.append("reference")
        wall = next(reference_walls)
        return {"wall_s": wall, "cpu_s": wall, "duration_s": 100.0, "rmse_m": 0.02}

    monkeypatch.setattr(bench, "replay", replay)
    monkeypatch.setattr(bench, "reference_run", reference_run)
    monkeypatch.setattr(bench, "flights_or_skip", lambda name, echo: [SimpleNamespace(name="F")])
    monkeypatch.setattr(bench, "imported_flight", lambda flight, work: None)
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
