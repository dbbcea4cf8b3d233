"""The flights of a batch as tasks of a Dask ``distributed`` cluster; the driver only collects the rows.

Embedded by default: a ``LocalCluster`` of one single-threaded worker process per core, its
scheduler on loopback with no dashboard, gone when the batch ends. Given a scheduler address
it runs on a cluster someone already has. Each task (:func:`~vtolpose.service.batch.task.run_flight`)
writes its flight's files itself and returns one small row. A worker that dies takes its flight
with it; the scheduler gives the flight to another worker, up to ``allowed_failures`` times,
then the flight is listed as failed with the reason (a flight too large for the worker's memory
limit is killed by its nanny each time and ends there).
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from vtolpose.service.batch.flights import FlightInput
from vtolpose.service.batch.settings import BatchSettings
from vtolpose.service.batch.task import clear_partials, run_flight

log = logging.getLogger(__name__)

ALLOWED_FAILURES = 2  # a flight whose worker dies is run again this many times before it counts as failed


@dataclass
class BatchState:
    """Where a batch is: flights finished (done, skipped, failed) out of the total, and its clock."""

    total: int
    workers: int = 1
    done: int = 0
    skipped: int = 0
    failed: int = 0
    started: float = field(default_factory=time.perf_counter)

    @property
    def finished(self) -> int:
        return self.done + self.skipped + self.failed

    @property
    def running(self) -> int:
        return min(self.workers, self.total - self.finished)

    def eta_s(self) -> float | None:
        """Time left at the rate of the flights run so far (skipped ones cost nothing and are not counted)."""
        worked = self.done + self.failed
        if worked == 0:
            return None
        return (time.perf_counter() - self.started) / worked * (self.total - self.finished)


ProgressCallback = Callable[[BatchState, dict[str, Any]], None]


@dataclass
class BatchOutcome:
    rows: list[dict[str, Any]]
    wall_s: float
    workers: int
    where: str  # "local cluster of N workers" or the scheduler's address


def _absolute(flight: FlightInput) -> FlightInput:
    """Workers may run elsewhere (shared storage, other working folders): paths go out absolute."""
    return FlightInput(flight.name, str(Path(flight.path).absolute()), flight.kind, flight.problem)


def _lost_row(flight: FlightInput, exc: BaseException, memory_limit: str | None) -> dict[str, Any]:
    from distributed import KilledWorker

    if isinstance(exc, KilledWorker):
        limit = f"{memory_limit} per worker" if memory_limit else "the cluster's per-worker limit"
        deaths = getattr(exc, "allowed_failures", ALLOWED_FAILURES) + 1  # the scheduler's setting, not ours on a cluster
        error = (f"KilledWorker: the worker running this flight died {deaths} times (killed, or above its "
                 f"memory limit, {limit}); not tried again")
    else:
        error = f"{type(exc).__name__}: {exc}"
    return {"flight": flight.name, "input": flight.path, "kind": flight.kind, "status": "failed", "error": error}


def local_cluster(workers: int | None, memory_limit: str | None):
    """A loopback-only cluster of single-threaded worker processes (no dashboard: nothing listens beyond the host)."""
    import dask
    from distributed import LocalCluster

    # No statistical profiler in the workers: it samples the running flight's stack every 10 ms, which
    # costs a replay (deep Python stacks, the GIL) and nobody reads it without a dashboard.
    with dask.config.set({"distributed.scheduler.allowed-failures": ALLOWED_FAILURES,
                          "distributed.worker.profile.enabled": False}):
        return LocalCluster(n_workers=workers or os.cpu_count() or 1, threads_per_worker=1, processes=True,
                            host="127.0.0.1", dashboard_address=None, memory_limit=memory_limit or "auto",
                            silence_logs=logging.ERROR,
                            # The scheduler's HTTP endpoints (health, metrics) start even without a dashboard:
                            # loopback and a free port, never a fixed one another batch may hold.
                            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})


def run_on_client(client, flights: list[FlightInput], settings: BatchSettings, out_root: str | Path,
                  force: bool = False, on_progress: ProgressCallback | None = None,
                  memory_limit: str | None = None) -> list[dict[str, Any]]:
    """Submit one task per flight to ``client``'s cluster; the rows in the flights' order as they finish."""
    from distributed import as_completed

    out_root = str(Path(out_root).absolute())
    flights = [_absolute(f) for f in flights]
    threads = client.nthreads()
    if any(n > 1 for n in threads.values()):
        log.warning("some workers run %d flights at once in one process (more memory each): start them with "
                    "--nthreads 1", max(threads.values()))
    state = BatchState(len(flights), workers=max(1, sum(threads.values())))
    token = os.urandom(4).hex()
    futures = {client.submit(run_flight, flight, settings, out_root, force, key=f"vtolpose-flight-{flight.name}-{token}",
                             pure=False): k for k, flight in enumerate(flights)}
    rows: list[dict[str, Any] | None] = [None] * len(flights)
    for future in as_completed(futures):
        k = futures[future]
        try:
            row = future.result()
        except Exception as exc:  # noqa: BLE001 - the worker died (KilledWorker) or the task was lost
            row = _lost_row(flights[k], exc, memory_limit)
            clear_partials(Path(out_root), flights[k].name)  # what its last attempt left
            state.workers = max(1, sum(client.nthreads().values()))  # workers died: count those there are now
        future.release()
        rows[k] = row
        state.done += row["status"] == "done"
        state.skipped += row["status"] == "skipped"
        state.failed += row["status"] == "failed"
        if on_progress is not None:
            on_progress(state, row)
    return [row for row in rows if row is not None]


def run_batch(flights: list[FlightInput], settings: BatchSettings, out_root: str | Path, scheduler: str | None = None,
              workers: int | None = None, memory_limit: str | None = None, force: bool = False,
              on_progress: ProgressCallback | None = None) -> BatchOutcome:
    """Run every flight on the embedded cluster, or on ``scheduler`` (``tcp://HOST:8786``)."""
    from distributed import Client

    started = time.perf_counter()
    if scheduler:
        with Client(scheduler, timeout="30s") as client:
            rows = run_on_client(client, flights, settings, out_root, force, on_progress, memory_limit)
            count = len(client.nthreads())
        return BatchOutcome(rows, time.perf_counter() - started, count, scheduler)
    with local_cluster(workers, memory_limit) as cluster, Client(cluster) as client:
        rows = run_on_client(client, flights, settings, out_root, force, on_progress, memory_limit)
        count = len(cluster.workers)
    return BatchOutcome(rows, time.perf_counter() - started, count, f"local cluster of {count} worker processes")


def run_in_loop(flights: list[FlightInput], settings: BatchSettings, out_root: str | Path,
                force: bool = False) -> list[dict[str, Any]]:
    """The same flights one after the other in this process: the yardstick for the engine's overhead."""
    return [run_flight(_absolute(flight), settings, str(Path(out_root).absolute()), force) for flight in flights]
