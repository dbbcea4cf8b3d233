"""``vtolpose bench --only camera-matrix``: Tests 1–3 over a matrix of simulated cameras and motions.

A test matrix this project owns rather than one renderer's defaults: a camera over a floor
(``drivers.simulator.floor``) textured with real recorded frames, three lenses, three
resolutions, 10–20 Hz, three motions and three kinds of start. Not the full product: a base cell
(gentle motion, radial-tangential 640 × 360 at 15 Hz, moving from the first sample, the V101
frames as texture), then one factor changed at a time (:data:`CELLS`).

Per cell one flight is simulated and rendered (seed 1), then replayed three times with the
default configuration and no per-cell setting: Test 1 IMU+GPS, Test 2 IMU+camera, Test 3
IMU+camera+GPS, each scored by the replay report from the first pose (Test 2 after its start is
put on the truth and its heading turned onto the truth's, as the report does). A cell passes
when Test 3 is no worse than Test 1 in position and in attitude, every test's NEES mean is inside
its band, and no test reset; the verdict names every condition that failed.

Textures from ``../shared/data`` (the V101 and hand-held frames): a cell whose frames are not
there is skipped with the reason.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import SimulationOptions, simulate_flight
from vtolpose.drivers.simulator.cameras import matrix_camera
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.drivers.simulator.floor import FloorScenario, start_options
from vtolpose.drivers.simulator.motion_profiles import PROFILES
from vtolpose.drivers.simulator.photo_mosaic import PhotoSource, shared_photo_sources
from vtolpose.service.bench.euroc import data_roots
from vtolpose.service.bench.rows import Row
from vtolpose.service.replay.report import build_report
from vtolpose.service.replay.session import replay
from vtolpose.service.runtime.kernels import load_compiled_kernels

SEED = 1
TESTS = (("Test 1", ["imu", "gps"]), ("Test 2", ["imu", "camera"]), ("Test 3", ["imu", "camera", "gps"]))
SAMPLES_TEXTURE = "samples"  # scikit-image's photographs: always there


@dataclass(frozen=True, slots=True)
class Cell:
    """One flight of the matrix: what it varies from the base, and its settings."""

    name: str
    profile: str = "gentle"
    lens: str = "radtan"
    width: int = 640
    height: int = 360
    rate_hz: float = 15.0
    start: str = "motion"
    texture: str = "v101"
    duration_s: float = 20.0

    def settings(self) -> str:
        return (f"{self.profile}, {self.lens} {self.width}×{self.height} @ {self.rate_hz:g} Hz, start {self.start}, "
                f"{self.texture}, {self.duration_s:g} s")


BASE = Cell("base")
CELLS: tuple[Cell, ...] = (
    BASE,
    replace(BASE, name="texture handheld", texture="handheld"),
    replace(BASE, name="texture samples", texture=SAMPLES_TEXTURE),
    replace(BASE, name="lens pinhole", lens="pinhole"),
    replace(BASE, name="lens equidistant", lens="equidistant"),
    replace(BASE, name="656×494", width=656, height=494),
    replace(BASE, name="1280×720", width=1280, height=720, duration_s=12.0),  # rendering and SIFT are slow there
    replace(BASE, name="10 Hz", rate_hz=10.0),
    replace(BASE, name="20 Hz", rate_hz=20.0),
    replace(BASE, name="hover", profile="hover"),
    replace(BASE, name="aggressive", profile="aggressive"),
    replace(BASE, name="start at rest", start="rest"),
    replace(BASE, name="start mid-flight", start="mid-flight"),
)


@dataclass(frozen=True, slots=True)
class TestScore:
    position_m: float | None
    attitude_deg: float | None
    nees_mean: float | None
    nees_in_band: float | None  # fraction of samples inside the per-sample band
    nees_mean_in_band: bool
    resets: int
    note: str = ""  # why there is no score, the first scored pose, the resets' events

    @classmethod
    def of(cls, report: dict) -> "TestScore":
        nees = report.get("nees")
        notes = []
        if "no_scores" in report:
            notes.append(report["no_scores"])
        if "first_scored_s" in report:
            notes.append(f"first scored pose at {report['first_scored_s']:.1f} s")
        if report.get("reset_counter"):  # what was counted: resets, and starts that replaced an initialising estimate
            notes += [f"{e['t_s']:.1f} s {e['message'][:120]}" for e in report.get("events", [])
                      if any(word in e["message"].lower() for word in ("reset", "start"))]
        return cls(report.get("position_rmse_m"), report.get("attitude_rmse_deg"),
                   None if nees is None else nees["nees_mean"], None if nees is None else nees["fraction_in_band"],
                   bool(nees and nees["mean_in_band"]), int(report.get("reset_counter", 0)), "; ".join(notes))

    def text(self) -> str:
        if self.position_m is None:
            return f"no scores, resets {self.resets}"
        nees = "—" if self.nees_mean is None else f"{self.nees_mean:.2f} / {100 * self.nees_in_band:.0f} %"
        attitude = "—" if self.attitude_deg is None else f"{self.attitude_deg:.2f}°"
        return f"{self.position_m:.4f} m, {attitude}, NEES {nees}, resets {self.resets}"


def verdict(scores: dict[str, TestScore]) -> list[str]:
    """The conditions a cell failed (empty: it passed)."""
    t1, t3 = scores["Test 1"], scores["Test 3"]
    failed = []
    for what, a, b in (("position", t3.position_m, t1.position_m), ("attitude", t3.attitude_deg, t1.attitude_deg)):
        if a is None or b is None or a > b:
            failed.append(f"Test 3 {what} > Test 1")
    for test, s in scores.items():
        if not s.nees_mean_in_band:
            failed.append(f"{test} NEES out of band")
        if s.resets:
            failed.append(f"{test} reset ×{s.resets}")
    return failed


def photo_root() -> Path:
    """The shared data folder that holds the texture recordings (the first of the EuRoC bench's roots that exists)."""
    roots = data_roots()
    return next((r for r in roots if r.is_dir()), roots[0])


def run_cell(cell: Cell, photos: PhotoSource | None, work: Path, echo: Callable[[str], None]) -> dict[str, TestScore]:
    """Simulate and render ``cell``'s flight into ``work``, replay Tests 1–3 with the default configuration."""
    profile = PROFILES[cell.profile]
    scenario = FloorScenario(profile=profile, photos=photos)
    options = SimulationOptions(imu=profile.imu_model(), **start_options(cell.start, scenario))
    t0 = time.perf_counter()
    flight = simulate_flight(scenario, cell.duration_s, SEED, options)
    camera = matrix_camera(cell.lens, cell.width, cell.height, cell.rate_hz)
    dataset = Dataset.open(write_flight(flight, work / "flight", overwrite=True, camera=camera))
    echo(f"    rendered {int(cell.duration_s * cell.rate_hz)} frames in {time.perf_counter() - t0:.0f} s")
    cfg = load_config(None, {})
    scores = {}
    for test, sensors in TESTS:
        t0 = time.perf_counter()
        scores[test] = score = TestScore.of(build_report(replay(dataset, cfg, sensors), dataset, cfg))
        echo(f"    {test}: {score.text()} ({time.perf_counter() - t0:.0f} s)" + (f"; {score.note}" if score.note else ""))
    return scores


def table_lines(results: list[tuple[Cell, dict[str, TestScore] | None, str]]) -> list[str]:
    """The matrix as a Markdown table: one row per cell, Tests 1–3 and the verdict."""
    lines = ["| cell | settings | Test 1 (pos, att, NEES mean / in band, resets) | Test 2 | Test 3 | verdict |",
             "|---|---|---|---|---|---|"]
    for cell, scores, skipped in results:
        if scores is None:
            lines.append(f"| {cell.name} | {cell.settings()} | — | — | — | skipped: {skipped} |")
            continue
        failed = verdict(scores)
        text = "PASS" if not failed else "FAIL: " + ", ".join(failed)
        lines.append(f"| {cell.name} | {cell.settings()} | " + " | ".join(scores[t].text() for t, _ in TESTS) + f" | {text} |")
    return lines


def bench_camera_matrix(cells: tuple[Cell, ...] = CELLS, echo: Callable[[str], None] = print) -> list[Row]:
    """Tests 1–3 per cell of :data:`CELLS`; prints progress per cell, then the table (long: rendered flights)."""
    sources = shared_photo_sources(photo_root())
    results: list[tuple[Cell, dict[str, TestScore] | None, str]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, cell in enumerate(cells, start=1):
            photos = None if cell.texture == SAMPLES_TEXTURE else sources[cell.texture]
            reason = photos.missing() if photos is not None else None
            echo(f"  [{i}/{len(cells)}] {cell.name}: {cell.settings()}" + (f": skipped, {reason}" if reason else ""))
            if reason:
                results.append((cell, None, reason))
                continue
            load_compiled_kernels()  # before the first replay's clock starts (cheap after the first call)
            t0 = time.perf_counter()
            results.append((cell, run_cell(cell, photos, Path(tmp), echo), ""))
            echo(f"    ({time.perf_counter() - t0:.0f} s)")
    for line in table_lines(results):
        echo("  " + line)
    rows = []
    for cell, scores, _ in results:
        if scores is None:
            continue
        t1, t3 = scores["Test 1"], scores["Test 3"]
        ratio = t3.position_m / t1.position_m if t1.position_m and t3.position_m is not None else float("nan")
        failed = verdict(scores)
        rows.append(Row(f"camera-matrix {cell.name}: Test 3 / Test 1 position", ratio, "x",
                        "PASS" if not failed else "FAIL: " + ", ".join(failed), "<= 1"))
    return rows
