"""Zenoh query load against the pose stream: does query work delay or lose a pose?

A landfill flight is replayed in real time through the runtime with the Zenoh output (its own
process, as ``vtolpose run --replay … --zenoh`` would), plus a probe output that stamps each pose
as it leaves: its lateness against the replay clock, and the gap to the previous pose, measure
what the query work costs the pose path inside the process (the interpreter lock, the history
lock). A subscriber in a second process counts the poses lost on the way (holes in ``seq``);
this process fires rounds of concurrent queries from one client session. The quiet phase is the
baseline of the same run; the loaded phases are given as ratios to it. Target: no pose lost and
no pose later than one IMU period (8 ms at 125 Hz) more than in the quiet phase.

Both ways of answering are measured in one run, each with a daemon of its own: in the query
process (``outputs.zenoh.query_process``, the default) and on the service's own thread.

Run: ``vtolpose bench --only zenoh-queries`` or ``python -m vtolpose.service.bench.zenoh_queries
[--realtime PRIORITY]`` (about 3 minutes). Absolute figures depend on the machine
and its load (the three processes share it): compare the ratios to the quiet phase.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable

import zenoh

from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight

Row = tuple[str, float, str, str]
PREFIX = "vtolpose/vtol1"

_DAEMON = r"""
import asyncio, json, sys, threading, time
import numpy as np
from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.service.runtime.daemon import build_runtime, serve
from vtolpose.service.runtime.sources import ReplayClock, ReplaySource

class Stamps:
    # An output after the Zenoh one: the moment each pose has left.
    name = "stamps"
    def __init__(self): self.rows = []
    def open(self): pass
    def publish(self, pose): self.rows.append((time.perf_counter(), pose.t_ns))
    def publish_status(self, status): pass
    async def serve(self, stop): await stop.wait()
    def close(self): pass

root, endpoint, duration = sys.argv[1], sys.argv[2], float(sys.argv[3])
priority = None if sys.argv[4] == "none" else int(sys.argv[4])
dataset = Dataset.open(root)
cfg = load_config(None, {"outputs": {"zenoh": {"enabled": True, "listen": [endpoint], "query_process": sys.argv[5] == "process"}},
                         "run": {"realtime_priority": priority}})
runtime = build_runtime(cfg, dataset.calibration, live=priority is not None)  # live: apply the priority
stamps = Stamps()
runtime.outputs.append(stamps)

def marks():
    done = 0
    for line in sys.stdin:
        rows, done = stamps.rows[done:], len(stamps.rows)
        wall = np.array([w for w, _ in rows]); t = np.array([t for _, t in rows], dtype=float) * 1e-9
        late = (wall - wall[0]) - (t - t[0]) if len(rows) > 1 else np.zeros(1)
        late -= late.min()
        gaps = np.diff(wall) if len(rows) > 1 else np.zeros(1)
        print(json.dumps({"late_p99_ms": 1e3 * float(np.percentile(late, 99)), "late_max_ms": 1e3 * float(late.max()),
                          "gap_max_ms": 1e3 * float(gaps.max())}), flush=True)

threading.Thread(target=marks, daemon=True).start()
print("ready", flush=True)
asyncio.run(serve(runtime, [ReplaySource(dataset, ["imu", "gps"], ReplayClock(1.0))], duration, handle_signals=False))
"""

_SUBSCRIBER = r"""
import json, sys, time, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
conf.insert_json5("scouting/multicast/enabled", "false")
s = zenoh.open(conf)
arrivals = []
s.declare_subscriber(sys.argv[2] + "/pose", lambda sample: arrivals.append(
    (time.perf_counter(), json.loads(sample.payload.to_string())["seq"])))
print("ready", flush=True)
for line in sys.stdin:  # "mark": report the arrivals since the last mark
    got, arrivals[:] = list(arrivals), []
    seqs = [q for _, q in got]
    lost = sum(b - a - 1 for a, b in zip(seqs, seqs[1:]) if b > a + 1)
    print(json.dumps({"poses": len(got), "lost": lost}), flush=True)
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_listening(port: int, proc: subprocess.Popen, timeout_s: float = 60.0) -> None:
    """Until the daemon accepts TCP connections on ``port`` (it opens its outputs after loading the data)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise RuntimeError(f"the daemon did not listen on port {port}: {proc.stderr.read() if proc.poll() is not None else ''}")


def _session(endpoint: str) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


class QueryLoad:
    """Rounds of ``concurrency`` simultaneous queries of ``selector`` until stopped; counts the answers."""

    def __init__(self, session: zenoh.Session, selector: Callable[[], str], concurrency: int) -> None:
        self.session, self.selector, self.concurrency = session, selector, concurrency
        self.ok = self.errors = self.silent = self.bytes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            pending = [self.session.get(self.selector(), timeout=5.0) for _ in range(self.concurrency)]
            for replies in pending:
                answered = False
                for reply in replies:
                    answered = True
                    if reply.ok is not None:
                        self.ok += 1
                        self.bytes += len(reply.ok.payload.to_bytes())
                    else:
                        self.errors += 1
                self.silent += not answered

    def __enter__(self) -> "QueryLoad":
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(30.0)


ANSWERED_BY = {"process": "answers in their own process", "thread": "answers on the service's thread"}


def bench_zenoh_queries(phase_s: float = 10.0, fill_s: float = 20.0, echo: Callable[[str], None] = print,
                        realtime_priority: int | None = None) -> list[Row]:
    """Pose lateness in the daemon and losses at a subscriber while a client floods the queryables.

    Twice in one run: with the windows answered in the query process (``outputs.zenoh.query_process``, the
    default) and on the service's own thread (the baseline).

    ``realtime_priority``: the daemon's loop under SCHED_FIFO as ``run.realtime_priority`` sets it
    on a vehicle (needs CAP_SYS_NICE), so that the machine's other load cannot delay it."""
    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "landfill"
        write_flight(simulate_flight("landfill", fill_s + 4 * phase_s + 30.0, 5), root)
        for answered_by in ANSWERED_BY:
            echo(f"  {ANSWERED_BY[answered_by]}:")
            quiet, phases = _phases(root, answered_by, phase_s, fill_s, echo, realtime_priority)
            rows += _rows(quiet, phases, ANSWERED_BY[answered_by])
    return rows


def _phases(root: Path, answered_by: str, phase_s: float, fill_s: float, echo: Callable[[str], None],
            realtime_priority: int | None) -> tuple[dict, dict[str, dict]]:
    """One daemon: the quiet phase, then each flood in turn."""
    port = _free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    total_s = fill_s + 5 * phase_s + 20.0
    daemon = subprocess.Popen([sys.executable, "-c", _DAEMON, str(root), endpoint, str(total_s),
                               str(realtime_priority) if realtime_priority is not None else "none", answered_by],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert daemon.stdout.readline().strip() == "ready", daemon.stderr.read()
    _wait_listening(port, daemon)
    subscriber = subprocess.Popen([sys.executable, "-c", _SUBSCRIBER, endpoint, PREFIX], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, text=True)
    try:
        assert subscriber.stdout.readline().strip() == "ready"
        session = _session(endpoint)
        newest = [0]
        session.declare_subscriber(f"{PREFIX}/pose", lambda s: newest.__setitem__(
            0, json.loads(s.payload.to_string())["t_ns"]))
        time.sleep(fill_s)  # the history fills

        def mark() -> dict:
            got = {}
            for proc in (daemon, subscriber):
                proc.stdin.write("mark\n")
                proc.stdin.flush()
                got.update(json.loads(proc.stdout.readline()))
            return got

        def phase(name: str, selector: Callable[[], str] | None, concurrency: int) -> dict:
            mark()
            load = QueryLoad(session, selector, concurrency) if selector else None
            if load is not None:
                with load:
                    time.sleep(phase_s)
            else:
                time.sleep(phase_s)
            got = mark()
            if load is not None:
                got.update(answered=load.ok, refused=load.errors, unanswered=load.silent, mb=load.bytes / 1e6)
            echo(f"    {name:<42} {json.dumps({k: round(v, 2) for k, v in got.items()})}")
            return got

        def whole() -> str:
            return f"{PREFIX}/trajectory?from=0;to={2**62}"

        def newest_10s() -> str:  # the largest window a mapper may ask for (outputs.zenoh.max_window_s)
            return f"{PREFIX}/trajectory?from={newest[0] - 10_000_000_000};to={newest[0] - 200_000_000}"

        def pose_at() -> str:
            return f"{PREFIX}/pose/at?t_ns={newest[0] - 200_000_000}"
        quiet = phase("quiet (baseline)", None, 0)
        phases = {
            "200 concurrent whole-history trajectory": phase("200 x whole history", whole, 200),
            "200 concurrent pose/at": phase("200 x pose/at", pose_at, 200),
            "50 concurrent 10 s windows": phase("50 x newest 10 s", newest_10s, 50),
        }
        session.close()
    finally:
        daemon.terminate()
        for proc in (daemon, subscriber):
            proc.stdin.close()
        for proc in (daemon, subscriber):
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
    return quiet, phases


def _rows(quiet: dict, phases: dict[str, dict], mode: str) -> list[Row]:
    rows: list[Row] = [(f"{mode}, quiet: latest pose (p99 / max)", quiet["late_max_ms"], "ms",
                        f"p99 {quiet['late_p99_ms']:.2f} ms; largest gap between poses {quiet['gap_max_ms']:.1f} ms")]
    for name, got in phases.items():
        rows.append((f"{mode}, {name}: latest pose", got["late_max_ms"], "ms",
                     f"{got['late_max_ms'] - quiet['late_max_ms']:+.2f} ms on quiet; p99 {got['late_p99_ms']:.2f} ms; "
                     f"largest gap {got['gap_max_ms']:.1f} ms; answered {got['answered']}"))
        rows.append((f"{mode}, {name}: poses lost", got["lost"], "poses", f"of {got['poses'] + got['lost']} at the subscriber"))
    return rows

if __name__ == "__main__":
    rt = int(sys.argv[sys.argv.index("--realtime") + 1]) if "--realtime" in sys.argv else None
    for label, value, unit, note in bench_zenoh_queries(realtime_priority=rt):
        print(f"  {label:<56} {value:>10.4g} {unit:<6} {note}")
