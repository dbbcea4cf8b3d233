"""The GTSAM speed reference of ``vtolpose bench --only euroc-reference`` (issue 16).

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
