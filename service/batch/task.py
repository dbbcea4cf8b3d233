"""One flight of a batch, start to finish: import, smoothed replay, map, scores, files; the table's row back.

:func:`run_flight` is what a Dask worker runs (or a plain loop, for comparison). It writes into
``OUT/.NAME.partial-<random suffix>`` and renames that to ``OUT/NAME`` only when every file is written, so
an output folder that exists is complete; ``batch.json`` in it holds the row and the flight's
fingerprint (:mod:`~vtolpose.service.batch.settings`), which lets the next batch skip it. Any
error in the flight becomes a failed row with its message: the batch goes on with the others.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import time
import uuid
from pathlib import Path
from typing import Any

from vtolpose.service.batch.flights import FlightInput
from vtolpose.service.batch.settings import BatchSettings, flight_fingerprint

DONE_FILE = "batch.json"
RUNNING_FILE = "running.json"  # in a partial folder: which host and process is writing it, since when


def partial_prefix(name: str) -> str:
    return f".{name}.partial-"


def read_done(out: Path, fingerprint: str) -> dict | None:
    """The stored row of a finished flight whose fingerprint matches, else None."""
    try:
        doc = json.loads((out / DONE_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return doc.get("row") if isinstance(doc, dict) and doc.get("fingerprint") == fingerprint else None


def _publish(work: Path, out: Path) -> None:
    """Put the finished ``work`` folder in ``out``'s place; an older result is moved aside first, then removed."""
    old = None
    if out.exists():
        old = out.parent / f".{out.name}.old-{uuid.uuid4().hex[:8]}"
        out.rename(old)
    work.rename(out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def clear_partials(out_root: Path, name: str) -> None:
    """Remove what an earlier attempt at this flight left (a worker killed mid-flight)."""
    for stale in out_root.glob(partial_prefix(name) + "*"):
        shutil.rmtree(stale, ignore_errors=True)


def run_flight(flight: FlightInput, settings: BatchSettings, out_root: str, force: bool = False) -> dict[str, Any]:
    """Process one flight into ``out_root/flight.name``; return its fleet-table row (``status``: done,
    skipped (unchanged since a finished run) or failed, with ``error``)."""
    started = time.perf_counter()
    base = {"flight": flight.name, "input": flight.path, "kind": flight.kind}
    root = Path(out_root)
    work: Path | None = None
    try:
        if flight.problem is not None:
            raise ValueError(flight.problem)
        fingerprint = flight_fingerprint(flight.path, settings)
        out = root / flight.name
        if not force:
            stored = read_done(out, fingerprint)
            if stored is not None:
                return {**stored, "status": "skipped"}
        root.mkdir(parents=True, exist_ok=True)
        clear_partials(root, flight.name)
        work = root / f"{partial_prefix(flight.name)}{uuid.uuid4().hex[:8]}"
        work.mkdir()
        where = {"host": socket.gethostname(), "pid": os.getpid()}
        (work / RUNNING_FILE).write_text(json.dumps({**where, "started_unix": time.time()}), encoding="utf-8")
        from vtolpose.service.batch.process import process_flight  # the estimator's imports, on the worker only

        row = {**base, **process_flight(flight, settings, work)}
        row.update(status="done", error=None, wall_s=round(time.perf_counter() - started, 3), **where)
        (work / DONE_FILE).write_text(json.dumps({"fingerprint": fingerprint, "row": row}, indent=2, default=str) + "\n",
                                      encoding="utf-8")
        (work / RUNNING_FILE).unlink()
        _publish(work, out)
        return row
    except Exception as exc:  # noqa: BLE001 - a flight's failure is its row's, never the batch's
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
        message = str(exc) or type(exc).__name__
        return {**base, "status": "failed", "error": f"{type(exc).__name__}: {message}",
                "wall_s": round(time.perf_counter() - started, 3)}
