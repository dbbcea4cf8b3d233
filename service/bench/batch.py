"""``vtolpose bench --only batch``: what the batch engine gains on this computer's cores, and what it costs.

Sixteen short simulated flights (landfill, IMU + GPS, smoothed, no camera, no LIDAR) run three ways
in the same process's lifetime: a plain loop in this process (the yardstick), then a local cluster
of one worker and one of two workers, each worker warmed first (imports, compiled kernels: once
per worker process, not per flight). The speed-up is the one-worker wall time over the two-worker
one; the engine's overhead per flight is the one-worker wall time minus the loop's, per flight.
Each way runs ROUNDS times, in turn, and its best time is the figure: other work on the machine
comes and goes within minutes, and the best round is the one least disturbed by it.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from vtolpose.config import load_config
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.service.bench.rows import Row
from vtolpose.service.batch.engine import local_cluster, run_in_loop, run_on_client
from vtolpose.service.batch.flights import FlightInput, find_flights
from vtolpose.service.batch.settings import BatchSettings
from vtolpose.service.batch.task import run_flight

FLIGHTS = 16
FLIGHT_S = 60.0
SPEEDUP_TARGET = ">= 1.8"
ROUNDS = 2


def _warm(flight: FlightInput, settings: BatchSettings, out_root: str) -> int:
    """One flight run in this process and thrown away: the imports and kernels a process loads once."""
    row = run_flight(flight, settings, out_root, force=True)
    if row["status"] != "done":
        raise RuntimeError(f"the warm-up flight failed: {row.get('error')}")
    return row["pid"]


def _on_cluster(workers: int, flights: list[FlightInput], settings: BatchSettings, root: Path) -> float:
    from distributed import Client

    with local_cluster(workers, None) as cluster, Client(cluster) as client:
        addresses = list(client.nthreads())  # a task pinned to each (client.run would run it on the worker's event loop)
        pids = client.gather([client.submit(_warm, flights[0], settings, str(root / f"warm-{workers}-{k}"),
                                            workers=[address], pure=False) for k, address in enumerate(addresses)])
        if len(set(pids)) != workers:
            raise RuntimeError(f"expected {workers} warmed worker processes, got {len(set(pids))}")
        started = time.perf_counter()
        rows = run_on_client(client, flights, settings, root / f"cluster-{workers}", force=True)
        wall = time.perf_counter() - started
    failed = [r for r in rows if r["status"] != "done"]
    if failed:
        raise RuntimeError(f"{len(failed)} flights failed on {workers} workers: {failed[0].get('error')}")
    return wall


def bench_batch() -> list[Row]:
    """`vtolpose batch`: 16 short flights on 1 and 2 workers (speed-up target ≥ 1.8×), the engine's overhead per flight against a plain loop"""
    settings = BatchSettings(load_config(None, {}), plots=False)
    with tempfile.TemporaryDirectory(prefix="vtolpose-bench-batch-") as tmp:
        root = Path(tmp)
        for k in range(FLIGHTS):
            write_flight(simulate_flight("landfill", FLIGHT_S, k + 1), root / "flights" / f"flight{k + 1:02d}")
        flights = find_flights([str(root / "flights" / "*")])
        _warm(flights[0], settings, str(root / "warm-loop"))
        walls: dict[str, list[float]] = {"loop": [], "1": [], "2": []}
        for _ in range(ROUNDS):
            started = time.perf_counter()
            rows = run_in_loop(flights, settings, root / "loop", force=True)
            walls["loop"].append(time.perf_counter() - started)
            if any(r["status"] != "done" for r in rows):
                raise RuntimeError("a flight failed in the plain loop")
            walls["1"].append(_on_cluster(1, flights, settings, root))
            walls["2"].append(_on_cluster(2, flights, settings, root))
    loop_s, one_s, two_s = (min(walls[k]) for k in ("loop", "1", "2"))
    rounds = {k: ", ".join(f"{w:.1f}" for w in v) for k, v in walls.items()}
    note = f"{FLIGHTS} flights of {FLIGHT_S:g} s, IMU+GPS smoothed; best of rounds"
    return [
        Row("batch: plain loop in one process", loop_s / FLIGHTS, "s/flight", f"{note} {rounds['loop']} s"),
        Row("batch: local cluster, 1 worker", one_s / FLIGHTS, "s/flight", f"rounds {rounds['1']} s"),
        Row("batch: local cluster, 2 workers", two_s / FLIGHTS, "s/flight", f"rounds {rounds['2']} s"),
        Row("batch: speed-up, 2 workers over 1", one_s / two_s, "x", "best rounds, same run", SPEEDUP_TARGET),
        Row("batch: engine overhead per flight (1 worker - loop)", (one_s - loop_s) / FLIGHTS * 1e3, "ms/flight",
            f"{100 * (one_s - loop_s) / loop_s:+.1f} % of the loop's time"),
    ]
