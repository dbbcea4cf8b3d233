"""``vtolpose bench --only camera-clock``: the camera's time offset estimated online, on two cells of the camera matrix.

The base cell (:data:`~vtolpose.service.bench.camera_matrix.BASE`: gentle motion, where an offset shows little)
and the aggressive one (fast turns: it shows a lot) are each rendered once; Test 2 (IMU+camera) and
Test 3 (IMU+camera+GPS) replay each with the configured offset right (0, as rendered) and 10 ms wrong, each with
the offset estimation off and on. A wrong configured offset of +10 ms stamps each frame 10 ms late: the residual
the filter should find is −10 ms. Reported per case: accuracy, NEES, and the estimated residual ± its sigma.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import SimulationOptions, simulate_flight
from vtolpose.drivers.simulator.cameras import matrix_camera
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.drivers.simulator.floor import FloorScenario, start_options
from vtolpose.drivers.simulator.motion_profiles import PROFILES
from vtolpose.drivers.simulator.photo_mosaic import shared_photo_sources
from vtolpose.service.bench.camera_matrix import BASE, SEED, Cell, TestScore, photo_root
from vtolpose.service.bench.rows import Row
from vtolpose.service.replay.report import build_report
from vtolpose.service.replay.session import replay
from vtolpose.service.runtime.kernels import load_compiled_kernels

WRONG_OFFSET_S = 0.010
CASES = (  # name, configured offset [s], estimation on
    ("right, off", 0.0, False),
    ("right, on", 0.0, True),
    ("10 ms wrong, off", WRONG_OFFSET_S, False),
    ("10 ms wrong, on", WRONG_OFFSET_S, True),
)
TESTS = (("Test 2", ["imu", "camera"]), ("Test 3", ["imu", "camera", "gps"]))
CELLS = (BASE, replace(BASE, name="aggressive", profile="aggressive"))


def render(cell: Cell, work: Path) -> Dataset:
    """``cell``'s flight simulated and rendered into ``work`` (as the camera matrix does)."""
    profile = PROFILES[cell.profile]
    photos = shared_photo_sources(photo_root())[cell.texture]
    reason = photos.missing()
    if reason:
        raise FileNotFoundError(f"the {cell.texture} texture: {reason}")
    scenario = FloorScenario(profile=profile, photos=photos)
    flight = simulate_flight(scenario, cell.duration_s, SEED, SimulationOptions(imu=profile.imu_model(),
                                                                               **start_options(cell.start, scenario)))
    camera = matrix_camera(cell.lens, cell.width, cell.height, cell.rate_hz)
    return Dataset.open(write_flight(flight, work / "flight", overwrite=True, camera=camera))


def replay_case(dataset: Dataset, sensors: list[str], offset_s: float, estimate: bool) -> tuple[TestScore, dict | None]:
    """One replay: the score and the estimated residual offset (ms, with sigma; None when not estimated)."""
    cfg = load_config(None, {"calibration": {"camera": {"time_offset_s": offset_s}},
                             "estimator": {"camera": {"estimate_time_offset": estimate}}})
    report = build_report(replay(dataset, cfg, sensors), dataset, cfg)
    return TestScore.of(report), (report.get("camera") or {}).get("time_offset_ms")


def bench_camera_clock(echo: Callable[[str], None] = print) -> list[Row]:
    """Base and aggressive cells, Tests 2 and 3: the camera time offset right and 10 ms wrong, its estimation off and on."""
    rows = []
    lines = ["| cell | case | test | position, attitude, NEES mean / in band, resets | offset residual (ms) |",
             "|---|---|---|---|---|"]
    for cell in CELLS:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            dataset = render(cell, Path(tmp))
            echo(f"  {cell.name}: rendered {cell.settings()} in {time.perf_counter() - t0:.0f} s")
            load_compiled_kernels()
            for case, offset_s, estimate in CASES:
                for test, sensors in TESTS:
                    t0 = time.perf_counter()
                    score, offset = replay_case(dataset, sensors, offset_s, estimate)
                    found = "—" if offset is None else f"{offset['estimate']:+.2f} ± {offset['sigma']:.2f}"
                    echo(f"  {cell.name}, {case}, {test}: {score.text()}, offset {found} ({time.perf_counter() - t0:.0f} s)")
                    lines.append(f"| {cell.name} | {case} | {test} | {score.text()} | {found} |")
                    if offset is not None:  # how many sigmas the estimate is from the true residual
                        error = abs(offset["estimate"] + offset_s * 1e3)
                        rows.append(Row(f"camera-clock {cell.name} {case} {test}: |estimate − true| / sigma",
                                        error / offset["sigma"], "x", "", "<= 3"))
    for line in lines:
        echo("  " + line)
    return rows
