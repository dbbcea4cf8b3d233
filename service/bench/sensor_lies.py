"""Sensors that lie about themselves, measured: the figures behind those rows of docs/faults.md's table.

``sensor-lies``: a 60 s landfill IMU+GPS flight (seed 1), replayed clean and with its files damaged
as a receiver or a device clock would damage them, each replayed as ``vtolpose replay D --sensors
imu,gps`` does:

- every GPS fix claims σ = 1e-300 m (a GST the receiver gets wrong, a driver reading the wrong field);
- the same from 20 s on only, played on the stream (``--fault gps-sigma:20:1000:1e-300``);
- the IMU clock steps forward by 10¹⁸ ns at 16 s (a device clock reset);
- the IMU clock steps back 5 s at 24 s (a recording spliced, a counter that wraps).

Each row: position RMSE against truth (and its ratio to the clean flight's), resets, and what was
counted or said (the GPS noise check's verdict, the clock steps undone, rows dropped).
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Callable

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import GPS_CSV, IMU_CSV, Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.service.bench.faults import FaultRun, traced_replay
from vtolpose.service.bench.rows import Row

DURATION_S, SEED = 60.0, 1


def damaged_copy(root: Path, out: Path, rel: str, edit: Callable[[list[str]], list[str]]) -> Path:
    """A copy of the dataset ``root`` whose ``rel`` data rows went through ``edit(fields) -> fields``."""
    shutil.copytree(root, out)
    lines = (out / rel).read_text().splitlines()
    (out / rel).write_text("\n".join([lines[0], *(",".join(edit(line.split(","))) for line in lines[1:])]) + "\n")
    return out


def stamps_stepped(t0_ns: int, at_s: float, step_ns: int) -> Callable[[list[str]], list[str]]:
    """Every row stamped ``at_s`` or later after ``t0_ns`` moved by ``step_ns``."""
    at_ns = t0_ns + int(at_s * 1e9)
    return lambda f: [str(int(f[0]) + step_ns) if int(f[0]) >= at_ns else f[0], *f[1:]]


def _row(name: str, run: FaultRun, clean_rmse: float, dataset: Dataset) -> Row:
    status = run.result.estimator.status()
    gps, imu = status.counts["gps"], status.counts["imu"]
    noise = status.gps_noise
    said = [f"resets {dict(status.health['resets']) or 0}",
            f"GPS rejected {gps['rejected']}", f"flagged {gps.get('flagged', {})}",
            f"IMU rejected {imu['rejected']}", f"rows dropped {dataset.skipped}"]
    if noise["fixes_adjusted"]:
        said.append(f"noise check: {noise['text'] or 'believed again'} ({noise['fixes_adjusted']} fixes weighed as measured)")
    for rel, steps in dataset.clock_steps.items():
        said += [f"{rel}: {step.describe()}" for step in steps]
    rmse = run.rmse()
    return (f"{name}: position RMSE", rmse, "m", f"{rmse / clean_rmse:.2f} x clean; " + "; ".join(said))


def bench_sensor_lies() -> list[Row]:
    """The three lies of the fault table (and the GPS lie from mid-flight), each against the clean flight."""
    cfg, sensors = load_config(), ["imu", "gps"]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "clean"
        flight = simulate_flight("landfill", DURATION_S, SEED)
        write_flight(flight, root)
        t0 = int(flight.imu.t_ns[0])
        clean_set = Dataset.open(root)
        clean = traced_replay(clean_set, cfg, sensors)
        rows: list[Row] = [(f"landfill imu,gps {DURATION_S:g} s: position RMSE without damage", clean.rmse(), "m",
                            "the reference; target for each lie: <= 1.5 x this")]
        cases = [
            ("every fix claims sigma 1e-300 m", GPS_CSV, lambda f: [*f[:4], "1e-300", "1e-300"]),
            ("IMU clock +1e18 ns at 16 s", IMU_CSV, stamps_stepped(t0, 16.0, 10**18)),
            ("IMU clock -5 s at 24 s", IMU_CSV, stamps_stepped(t0, 24.0, -5 * 10**9)),
        ]
        for k, (name, rel, edit) in enumerate(cases):
            dataset = Dataset.open(damaged_copy(root, Path(tmp) / f"damaged{k}", rel, edit))
            rows.append(_row(name, traced_replay(dataset, cfg, sensors), clean.rmse(), dataset))
        lie = "gps-sigma:20:1000:1e-300"
        rows.append(_row(f"--fault {lie}", traced_replay(clean_set, cfg, sensors, [lie]), clean.rmse(), clean_set))
    return rows
