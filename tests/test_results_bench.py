"""``vtolpose bench --only results``: its rows in docs/results.md's layout, its quotes of the doc, its registration.

Made-up reports stand in for replays, so nothing here renders or replays a flight.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

from vtolpose.estimator import EventKind
from vtolpose.estimator.modes import FilterMode
from vtolpose.estimator.status import EstimatorEvent
from vtolpose.service.bench.results import tables, what_happens
from vtolpose.service.bench.results_tables import (
    DOCS_CAMERA_TESTS_CELLS, DOCS_IN_FLIGHT_CELLS, DOCS_TEST1_CELLS, camera_test_line, gps_test_line, in_flight_line,
)
from vtolpose.service.bench.runner import BENCHMARKS, LONG_BENCHMARKS
from vtolpose.service.cli import build_parser

RESULTS_MD = Path(__file__).resolve().parent.parent / "docs" / "results.md"


def _report(**figures) -> dict:
    nees = figures.pop("nees", None)
    report = dict(figures)
    if nees is not None:
        mean, in_band, share = nees
        report["nees"] = {"nees_mean": mean, "mean_in_band": in_band, "fraction_in_band": share}
    return report


def test_a_test1_row_has_the_docs_columns_and_the_docs_figures_last():
    report = _report(position_rmse_m=0.02031, gps_rmse_m=0.03942, position_rmse_over_gps=0.5152,
                     attitude_rmse_deg=0.4141, nees=(6.204, True, 0.9))
    assert gps_test_line("book 120 s", "thesis", report) == (
        "| book 120 s | thesis | 0.0203 m | 0.0394 m | 0.52 | 0.414° | 6.20 | 0.0203 m; 0.0394 m; 0.52; 0.414°; 6.20 |")


def test_metres_keep_three_decimals_above_ten_centimetres_and_a_nees_out_of_band_says_so():
    report = _report(position_rmse_m=0.4812, gps_rmse_m=2.0049, position_rmse_over_gps=0.24,
                     attitude_rmse_deg=2.412, nees=(23.71, False, 0.3))
    assert gps_test_line("landfill 300 s", "thesis", report).startswith(
        "| landfill 300 s | thesis | 0.481 m | 2.005 m | 0.24 | 2.41° | 23.71 (outside the band) |")


def test_a_row_without_a_figure_shows_a_dash_and_a_row_the_doc_lacks_has_no_docs_figures():
    assert gps_test_line("book 12 s", "biases", {}) == "| book 12 s | biases | — | — | — | — | — | — |"


def test_test2_rows_show_the_drift_and_test3_rows_the_gain_over_test1():
    camera_only = _report(position_rmse_m=0.0606, final_drift_m=0.0648, drift_percent=0.1286, distance_travelled_m=50.41,
                          attitude_rmse_deg=0.4644, nees=(8.523, True, 0.8))
    assert camera_test_line(2, "book", "thesis", camera_only, None) == (
        "| 2 | book | thesis | 0.0606 m |  | 0.0648 m (0.13 % of 50.4 m) | 0.464° | 8.52 | "
        "0.0342 m; 0.0365 m (0.072 % of 50.4 m); 0.435°; 6.98 |")  # the figures the doc shows beside it
    with_gps = _report(position_rmse_m=0.364, attitude_rmse_deg=0.479, nees=(10.07, True, 0.8))
    assert camera_test_line(3, "landfill", "thesis", with_gps, {"position_rmse_m": 0.5}) == (
        "| 3 | landfill | thesis | 0.364 m | 0.73 × |  | 0.479° | 10.07 | 0.324 m; 0.67 ×; 0.454°; 8.28 |")
    assert "| — |" in camera_test_line(3, "book", "biases", with_gps, None)


def test_an_in_flight_row_gives_millimetres_on_the_book_the_placed_heading_in_brackets_and_the_band_share():
    report = _report(position_rmse_m=0.01759, attitude_rmse_deg=1.370, attitude_rmse_with_heading_deg=0.6688,
                     nees=(4.322, True, 0.9133))
    assert in_flight_line("book", "imu,gps", report, "heading placed at 4.5 s") == (
        "| book | imu,gps | 17.6 mm | 1.37° (0.669°) | 4.32 (91 %) | heading placed at 4.5 s | "
        "17.7 mm; 1.92° (0.675°); 4.24 (90 %) |")  # the figures the doc shows beside it
    landfill = _report(position_rmse_m=6.634, attitude_rmse_deg=1.161, nees=(21.3, False, 0.17))
    assert in_flight_line("landfill", "imu,camera", landfill, "x").startswith("| landfill | imu,camera | 6.63 m | 1.16° | 21.30 (17 %) | x |")


@pytest.mark.parametrize("cells, row", [
    *[(cells, f"| {dataset} | {model} | " + " | ".join(cells) + " |") for (dataset, model), cells in DOCS_TEST1_CELLS.items()],
    *[(cells, f"| {test} | {dataset} | {model} | {cells[0]} | " + (f"| {cells[1]} |" if test == 2 else f"{cells[1]} | |")
       + f" {cells[2]} | {cells[3]} |") for (test, dataset, model), cells in DOCS_CAMERA_TESTS_CELLS.items()],
    *[(cells, f"| {flight} | {sensors} | " + " | ".join(cells) + " |") for (flight, sensors), cells in DOCS_IN_FLIGHT_CELLS.items()],
])
def test_the_docs_column_quotes_docs_results_md_as_it_stands(cells, row):
    assert any(line.startswith(row) for line in RESULTS_MD.read_text(encoding="utf-8").splitlines()), row


def test_the_tables_come_in_the_docs_order_of_sections_and_rows():
    gps = {(f"{s} {d} s", m): f"T1 {s} {m}" for s, d in (("landfill", 300), ("book", 120)) for m in ("biases", "thesis")}
    camera = {(3, "landfill", "biases"): "T3 landfill biases", (2, "book", "thesis"): "T2 book thesis",
              (3, "book", "thesis"): "T3 book thesis"}
    in_flight = {("landfill", "imu,gps"): "A landfill gps", ("book", "imu,camera"): "A book camera",
                 ("book", "imu,gps"): "A book gps"}
    rows = [line for line in tables(gps, camera, in_flight) if line and not line.startswith(("|", "#"))]
    assert rows == ["T1 book thesis", "T1 book biases", "T1 landfill thesis", "T1 landfill biases",
                    "T2 book thesis", "T3 book thesis", "T3 landfill biases",
                    "A book camera", "A book gps", "A landfill gps"]


def _replayed_with(events: list[EstimatorEvent], mode: FilterMode) -> SimpleNamespace:
    status = SimpleNamespace(events=tuple(events), mode=mode,
                             first=lambda kind: next((e for e in events if e.kind is kind), None))
    return SimpleNamespace(estimator=SimpleNamespace(status=lambda: status), data_t0_ns=1_000_000_000)


def test_what_happens_tells_the_start_the_heading_and_the_resets_from_the_estimators_events():
    events = [EstimatorEvent(4_000_000_000, EventKind.STARTED,
                             "started from 251 IMU samples, moving (GPS); g = 9.8066 m/s^2", 0),
              EstimatorEvent(5_500_000_000, EventKind.HEADING_PLACED, "heading placed from 14 GPS fixes", 0),
              EstimatorEvent(9_000_000_000, EventKind.RESET, "reset #1: refused", 1, "gps_rejected")]
    assert what_happens(_replayed_with(events, FilterMode.GPS)) == (
        "started at 3.0 s, moving (GPS); heading placed at 4.5 s; 1 resets (gps_rejected); ends gps")


def test_a_wait_for_the_visual_inertial_start_is_told_before_it():
    events = [EstimatorEvent(1_900_000_000, EventKind.INITIALISING, "started from 240 IMU samples, moving (camera), from the "
                             "mean specific force; no state until the visual-inertial start; g = 9.8066 m/s^2", 0),
              EstimatorEvent(2_600_000_000, EventKind.STARTED, "visual-inertial start from 12 frames over 1.5 s, ...", 0)]
    assert what_happens(_replayed_with(events, FilterMode.LOCAL)) == (
        "initialising from 0.9 s (moving, camera only: no state); visual-inertial start at 1.6 s; 0 resets; ends local")
    assert what_happens(_replayed_with(events[:1], FilterMode.INITIALISING)) == (
        "initialising from 0.9 s (moving, camera only: no state); 0 resets; ends initialising")


def test_the_results_bench_is_registered_as_long_and_listed_in_the_help(capsys):
    assert "results" in BENCHMARKS and "results" in LONG_BENCHMARKS
    with pytest.raises(SystemExit):
        build_parser().parse_args(["bench", "--help"])
    listing = capsys.readouterr().out
    assert any(line.split()[:1] == ["results"] and "docs/results.md" in line for line in listing.splitlines())
