"""The three accuracy tables of docs/results.md, written from replay reports in the doc's own layout.

Each row ends with a "docs" column: the figures docs/results.md shows for that row today, quoted
as the doc writes them, so a reader sees at a glance which figures have moved since they were
measured. The figures come from :func:`~vtolpose.service.replay.report.build_report`'s keys, the
same ones ``vtolpose replay --report`` writes.
"""

from __future__ import annotations

import math
from typing import Any

Report = dict[str, Any]

MISSING = "—"

# The doc's cells, verbatim, per row of "Test 1: IMU + GPS": position RMSE, GPS alone, ratio, attitude RMSE, NEES mean.
DOCS_TEST1_CELLS: dict[tuple[str, str], tuple[str, ...]] = {
    ("book 120 s", "thesis"): ("0.0203 m", "0.0394 m", "0.52", "0.414°", "6.20"),
    ("book 120 s", "biases"): ("0.0141 m", "0.0394 m", "0.36", "0.312°", "6.06"),
    ("landfill 300 s", "thesis"): ("0.481 m", "2.005 m", "0.24", "2.41°", "23.7 (outside the band)"),
    ("landfill 300 s", "biases"): ("0.388 m", "2.005 m", "0.19", "0.958°", "8.93"),
}

# The doc's cells per row of "Test 2 ... and Test 3": position RMSE, vs Test 1 or final drift, attitude RMSE, NEES mean.
DOCS_CAMERA_TESTS_CELLS: dict[tuple[int, str, str], tuple[str, ...]] = {
    (2, "book", "thesis"): ("0.0342 m", "0.0365 m (0.072 % of 50.4 m)", "0.435°", "6.98"),
    (2, "book", "biases"): ("0.0125 m", "0.0136 m (0.027 %)", "0.229°", "3.24"),
    (3, "book", "thesis"): ("0.0038 m", "0.19 ×", "0.407°", "7.61"),
    (3, "book", "biases"): ("0.0035 m", "0.25 ×", "0.347°", "5.97"),
    (3, "landfill", "thesis"): ("0.324 m", "0.67 ×", "0.454°", "8.28"),
    (3, "landfill", "biases"): ("0.249 m", "0.64 ×", "0.428°", "7.38"),
}

# The doc's cells per row of "Starting in the air": position RMSE, attitude RMSE (once placed), NEES mean (in band).
DOCS_IN_FLIGHT_CELLS: dict[tuple[str, str], tuple[str, ...]] = {
    ("book", "imu,camera"): ("2.8 mm", "0.153°", "1.63 (52 %)"),
    ("landfill", "imu,camera"): ("6.78 m", "0.429°", "4.03 (99 %)"),
    ("book", "imu,gps"): ("17.7 mm", "1.92° (0.675°)", "4.24 (90 %)"),
    ("landfill", "imu,gps"): ("0.55 m", "11.0° (5.50°)", "7.37 (85 %)"),
    ("book", "imu,camera,gps"): ("8.8 mm", "1.86° (0.452°)", "2.75 (76 %)"),
    ("landfill", "imu,camera,gps"): ("0.49 m", "9.92° (1.58°)", "6.30 (88 %)"),
}

TEST1_HEADER = ("| dataset | model | position RMSE | GPS alone | ratio | attitude RMSE | NEES mean | docs |",
                "|---|---|---|---|---|---|---|---|")
CAMERA_TESTS_HEADER = ("| test | dataset | model | position RMSE | vs Test 1 | final drift | attitude RMSE | NEES mean | docs |",
                       "|---|---|---|---|---|---|---|---|---|")
IN_FLIGHT_HEADER = ("| flight | sensors | position RMSE | attitude RMSE | NEES mean (in band) | what happens | docs |",
                    "|---|---|---|---|---|---|---|")


def _known(value: Any) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)


def metres(value: Any) -> str:
    """Four decimals below 10 cm, three above: the precision the doc's tables give."""
    if not _known(value):
        return MISSING
    return f"{value:.4f} m" if abs(value) < 0.1 else f"{value:.3f} m"


def millimetres_or_metres(value: Any) -> str:
    """The in-flight table's style: millimetres for the book's centimetre errors, metres for the landfill's."""
    if not _known(value):
        return MISSING
    return f"{value * 1e3:.1f} mm" if abs(value) < 0.1 else f"{value:.2f} m"


def degrees(value: Any) -> str:
    return f"{value:#.3g}°" if _known(value) else MISSING


def nees_text(report: Report) -> str:
    """NEES mean, and a warning when it lies outside its 95 % band, as the doc marks it."""
    nees = report.get("nees")
    if nees is None:
        return MISSING
    return f"{nees['nees_mean']:.2f}" + ("" if nees["mean_in_band"] else " (outside the band)")


def nees_with_band_share(report: Report) -> str:
    """NEES mean with the share of samples inside the per-sample 95 % band."""
    nees = report.get("nees")
    if nees is None:
        return MISSING
    return f"{nees['nees_mean']:.2f} ({100 * nees['fraction_in_band']:.0f} %)"


def docs_cell(cells: tuple[str, ...] | None) -> str:
    return "; ".join(cells) if cells else MISSING


def gps_test_line(dataset: str, model: str, report: Report) -> str:
    """One row of "Test 1: IMU + GPS"."""
    ratio = report.get("position_rmse_over_gps")
    return (f"| {dataset} | {model} | {metres(report.get('position_rmse_m'))} | {metres(report.get('gps_rmse_m'))} | "
            f"{f'{ratio:.2f}' if _known(ratio) else MISSING} | {degrees(report.get('attitude_rmse_deg'))} | "
            f"{nees_text(report)} | {docs_cell(DOCS_TEST1_CELLS.get((dataset, model)))} |")


def final_drift(report: Report) -> str:
    """Where the flight ended against the truth, and as a share of the distance flown."""
    drift, percent, distance = (report.get(k) for k in ("final_drift_m", "drift_percent", "distance_travelled_m"))
    if not _known(drift):
        return MISSING
    share = f" ({percent:.2g} % of {distance:.1f} m)" if _known(percent) and _known(distance) else ""
    return metres(drift) + share


def camera_test_line(test: int, dataset: str, model: str, report: Report, test1: Report | None) -> str:
    """One row of "Test 2 ... and Test 3": Test 2 shows its drift (no GPS), Test 3 its gain over Test 1."""
    position = report.get("position_rmse_m")
    against = ""
    if test == 3:
        base = (test1 or {}).get("position_rmse_m")
        against = f"{position / base:.2f} ×" if _known(position) and _known(base) and base > 0 else MISSING
    drift = final_drift(report) if test == 2 else ""
    return (f"| {test} | {dataset} | {model} | {metres(position)} | {against} | {drift} | "
            f"{degrees(report.get('attitude_rmse_deg'))} | {nees_text(report)} | "
            f"{docs_cell(DOCS_CAMERA_TESTS_CELLS.get((test, dataset, model)))} |")


def in_flight_attitude(report: Report) -> str:
    """Attitude RMSE, and in brackets the same once the heading is placed (when it was placed)."""
    text = degrees(report.get("attitude_rmse_deg"))
    placed = report.get("attitude_rmse_with_heading_deg")
    return text + (f" ({degrees(placed)})" if _known(placed) else "")


def in_flight_line(flight: str, sensors: str, report: Report, what_happens: str) -> str:
    """One row of "Starting in the air"."""
    return (f"| {flight} | {sensors} | {millimetres_or_metres(report.get('position_rmse_m'))} | "
            f"{in_flight_attitude(report)} | {nees_with_band_share(report)} | {what_happens} | "
            f"{docs_cell(DOCS_IN_FLIGHT_CELLS.get((flight, sensors)))} |")
