"""``results``: the headline accuracy tables of docs/results.md measured again on the code as it is.

Test 1 (IMU + GPS), Tests 2 and 3 (IMU + camera, with and without GPS) and "Starting in the air" were
each measured by hand with ``vtolpose simulate`` and ``vtolpose replay --report``, some of them
long ago. This bench makes the same flights (seed 1, camera frames rendered, each flight once per
run in a temporary folder), replays them with the same sensors, models and settings through the
same library calls those commands make, and prints the three tables in the doc's layout with the
doc's current figures beside them, so one command checks every figure of those tables.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any, Callable

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import SimulationOptions, make_scenario, simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.drivers.simulator.render import default_camera
from vtolpose.estimator import EventKind
from vtolpose.service.bench.results_tables import (
    CAMERA_TESTS_HEADER, DOCS_CAMERA_TESTS_CELLS, DOCS_IN_FLIGHT_CELLS, DOCS_TEST1_CELLS, IN_FLIGHT_HEADER,
    TEST1_HEADER, camera_test_line, gps_test_line, in_flight_line, metres, degrees, nees_text,
)
from vtolpose.service.bench.rows import Row
from vtolpose.service.replay.report import build_report
from vtolpose.service.replay.session import ReplayResult, replay
from vtolpose.service.runtime.kernels import load_compiled_kernels

Report = dict[str, Any]
Echo = Callable[[str], None]

SEED = 1  # every figure of docs/results.md is for seed 1
FULL_FLIGHTS = (("book", 120.0), ("landfill", 300.0))  # Tests 1-3
IN_FLIGHT_FLIGHTS = (("book", 40.0), ("landfill", 60.0))  # starting in the air, at the scenario's in-flight point
MODELS = ("thesis", "biases")
GPS_TEST_SENSORS = ("imu", "gps")
CAMERA_TESTS = ((2, ("imu", "camera")), (3, ("imu", "camera", "gps")))
CAMERA_ONLY_TEST_SCENARIOS = ("book",)  # the doc's Test 2 rows are the book's only
IN_FLIGHT_SENSOR_SETS = (("imu", "camera"), ("imu", "gps"), ("imu", "camera", "gps"))
IN_FLIGHT_SETTINGS = {"features": {"detector": "orb"}}  # the doc's `--set features.detector=orb`


def flushed_print(line: str) -> None:
    """Progress must reach a log file as it happens, not when the buffer fills."""
    print(line, flush=True)


class Stopwatch:
    """Progress lines with the time since the bench started: a quarter of an hour should not be silent."""

    def __init__(self, echo: Echo) -> None:
        self.echo = echo
        self.started = time.perf_counter()

    def say(self, text: str) -> None:
        self.echo(f"  results [{time.perf_counter() - self.started:6.0f} s] {text}")


def rendered_flight(scenario: str, duration_s: float, root: Path, in_flight: bool) -> Dataset:
    """``vtolpose simulate --scenario S --duration D --seed 1 [--start-in-flight]``, camera frames included."""
    options = SimulationOptions(start_s=make_scenario(scenario).in_flight_s) if in_flight else SimulationOptions()
    folder = root / f"{scenario}-{'in-flight' if in_flight else 'full'}"
    write_flight(simulate_flight(scenario, duration_s, SEED, options), folder, camera=default_camera())
    return Dataset.open(folder)


def what_happens(result: ReplayResult) -> str:
    """The start-up as the estimator told it: a wait for the visual start, how and when it started, the GPS
    joining, the heading's placement, resets, and the mode it ends in."""
    status = result.estimator.status()

    def at(t_ns: int) -> str:
        return f"{(t_ns - result.data_t0_ns) * 1e-9:.1f} s"

    parts: list[str] = []
    waited = status.first(EventKind.INITIALISING)
    if waited is not None:
        parts.append(f"initialising from {at(waited.t_ns)} (moving, camera only: no state)")
    started = status.first(EventKind.STARTED)
    if started is not None:  # "started from N IMU samples, HOW; g = ..." or "visual-inertial start from ..."
        head, _, rest = started.message.partition(" from ")
        how = rest.split("; g = ")[0].partition(", ")[2] if head == "started" else ""
        parts.append(f"{head} at {at(started.t_ns)}" + (f", {how}" if how else ""))
    for kind, said in ((EventKind.GPS_JOINED, "GPS joined"), (EventKind.HEADING_PLACED, "heading placed")):
        event = status.first(kind)
        if event is not None:
            parts.append(f"{said} at {at(event.t_ns)}")
    resets = [e.reset_kind or "reset" for e in status.events if e.kind is EventKind.RESET]
    parts.append(f"{len(resets)} resets" + (f" ({', '.join(sorted(set(resets)))})" if resets else ""))
    parts.append(f"ends {status.mode.value}")
    return "; ".join(parts)


def replayed(dataset: Dataset, sensors: tuple[str, ...], settings: dict) -> tuple[Report, str]:
    """``vtolpose replay DATASET --sensors ... [--variant/--set ...] --report r.json``: the report, and the start-up's
    story."""
    cfg = load_config(None, settings)
    result = replay(dataset, cfg, list(sensors))
    return build_report(result, dataset, cfg), what_happens(result)


def headline(report: Report) -> str:
    return (f"{metres(report.get('position_rmse_m'))}, {degrees(report.get('attitude_rmse_deg'))}, "
            f"NEES {nees_text(report)}; {report['wall_s']:.0f} s wall")


def position_row(table: str, label: str, report: Report, docs: tuple[str, ...] | None) -> Row:
    """A figure for the runner's list: the position RMSE against the doc's."""
    return Row(f"{table} {label}: position RMSE", float(report.get("position_rmse_m", float("nan"))), "m",
               f"docs {docs[0]}" if docs else "not in the docs")


def run_full_flights(root: Path, clock: Stopwatch) -> tuple[dict[tuple, str], dict[tuple, str], list[Row]]:
    """Tests 1, 2 and 3 on the book and the landfill: the rows of the first two tables, by their keys."""
    gps_lines: dict[tuple, str] = {}
    camera_lines: dict[tuple, str] = {}
    rows: list[Row] = []
    for scenario, duration_s in FULL_FLIGHTS:
        label = f"{scenario} {duration_s:g} s"
        clock.say(f"rendering {label}, seed {SEED}, camera frames included ...")
        dataset = rendered_flight(scenario, duration_s, root, in_flight=False)
        gps_reports: dict[str, Report] = {}
        for model in MODELS:
            clock.say(f"{label} Test 1 ({','.join(GPS_TEST_SENSORS)}), {model} ...")
            report, _ = replayed(dataset, GPS_TEST_SENSORS, {"estimator": {"variant": model}})
            gps_reports[model] = report
            gps_lines[(label, model)] = gps_test_line(label, model, report)
            rows.append(position_row("Test 1", f"{label} {model}", report, DOCS_TEST1_CELLS.get((label, model))))
            clock.say(f"  {headline(report)}")
        for test, sensors in CAMERA_TESTS:
            if test == 2 and scenario not in CAMERA_ONLY_TEST_SCENARIOS:
                continue
            for model in MODELS:
                clock.say(f"{label} Test {test} ({','.join(sensors)}), {model} ...")
                report, _ = replayed(dataset, sensors, {"estimator": {"variant": model}})
                camera_lines[(test, scenario, model)] = camera_test_line(test, scenario, model, report, gps_reports[model])
                rows.append(position_row(f"Test {test}", f"{scenario} {model}", report,
                                         DOCS_CAMERA_TESTS_CELLS.get((test, scenario, model))))
                clock.say(f"  {headline(report)}")
    return gps_lines, camera_lines, rows


def run_in_flight_starts(root: Path, clock: Stopwatch) -> tuple[dict[tuple, str], list[Row]]:
    """The flights that start in the air, with each sensor set: the rows of the third table, by their keys."""
    lines: dict[tuple, str] = {}
    rows: list[Row] = []
    for scenario, duration_s in IN_FLIGHT_FLIGHTS:
        clock.say(f"rendering {scenario} {duration_s:g} s --start-in-flight, seed {SEED}, camera frames included ...")
        dataset = rendered_flight(scenario, duration_s, root, in_flight=True)
        for sensors in IN_FLIGHT_SENSOR_SETS:
            named = ",".join(sensors)
            clock.say(f"{scenario} in flight, {named}, ORB ...")
            report, story = replayed(dataset, sensors, IN_FLIGHT_SETTINGS)
            lines[(scenario, named)] = in_flight_line(scenario, named, report, story)
            rows.append(position_row("in flight", f"{scenario} {named}", report, DOCS_IN_FLIGHT_CELLS.get((scenario, named))))
            clock.say(f"  {headline(report)}; {story}")
    return lines, rows


def tables(gps_lines: dict[tuple, str], camera_lines: dict[tuple, str], in_flight_lines: dict[tuple, str]) -> list[str]:
    """The three tables in the doc's order of sections and rows."""
    out = ["## Test 1: IMU + GPS", "", *TEST1_HEADER]
    out += [gps_lines[key] for key in ((f"{s} {d:g} s", m) for s, d in FULL_FLIGHTS for m in MODELS) if key in gps_lines]
    out += ["", "## Test 2: IMU + camera, and Test 3: IMU + camera + GPS (book 120 s, landfill 300 s)", "",
            *CAMERA_TESTS_HEADER]
    out += [camera_lines[key] for key in ((t, s, m) for t, _ in CAMERA_TESTS for s, _ in FULL_FLIGHTS for m in MODELS)
            if key in camera_lines]
    out += ["", "## Starting in the air", "", *IN_FLIGHT_HEADER]
    out += [in_flight_lines[key] for key in ((s, ",".join(n)) for n in IN_FLIGHT_SENSOR_SETS for s, _ in IN_FLIGHT_FLIGHTS)
            if key in in_flight_lines]
    return out


def bench_results(echo: Echo = flushed_print) -> list[Row]:
    """The tables of docs/results.md again: Tests 1-3 and the starts in the air (the doc's figures beside)."""
    load_compiled_kernels()  # once per process, before the first replay
    clock = Stopwatch(echo)
    with tempfile.TemporaryDirectory(prefix="vtolpose-results-") as tmp:
        gps_lines, camera_lines, rows = run_full_flights(Path(tmp), clock)
        in_flight_lines, in_flight_rows = run_in_flight_starts(Path(tmp), clock)
    for line in tables(gps_lines, camera_lines, in_flight_lines):
        echo("  " + line if line else "")
    return rows + in_flight_rows
