"""``cold-start``: what a user meets the first time, with an empty kernel cache, against the second time.

Each figure is a whole ``vtolpose`` process as a user starts it (interpreter, imports, kernels, data), in an
empty ``NUMBA_CACHE_DIR`` of its own: the first IMU+GPS replay of a flight against the second (the issue's
target: at most 1.5 × its wall time), the foreground compile of every kernel (``vtolpose warmup``), and the
daemon's time from its start to its first ODOMETRY on UDP (``run --replay``, as fast as the data allows),
cold and warm (target: within 3 s). A background compiler a cold run starts is waited for before the next
figure, so no figure shares the machine with it unless it says so.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from vtolpose.service.bench.rows import Row

VTOLPOSE = (sys.executable, "-m", "vtolpose")
ODOMETRY_ID = 331  # MAVLink 2 only
FIRST_POSE_TIMEOUT_S = 120.0
RATIO_TARGET = "<= 1.5"
FIRST_POSE_TARGET = "<= 3"


def _env(cache: Path) -> dict[str, str]:
    return dict(os.environ, NUMBA_CACHE_DIR=str(cache))


def _timed(args: list[str], cache: Path) -> float:
    """Wall seconds of one ``vtolpose`` process (which must succeed)."""
    started = time.perf_counter()
    subprocess.run([*VTOLPOSE, *args], env=_env(cache), check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    return time.perf_counter() - started


def _wait_for_compiler(cache: Path) -> float:
    """Seconds until a background compiler filling ``cache`` has finished (``warmup`` waits for its lock)."""
    return _timed(["-q", "warmup"], cache)


def _first_odometry_s(flight: Path, cache: Path) -> float:
    """Seconds from starting ``vtolpose run --replay`` to the first ODOMETRY it sends."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        udp.bind(("127.0.0.1", 0))
        udp.settimeout(0.05)
        port = udp.getsockname()[1]
        started = time.perf_counter()
        daemon = subprocess.Popen([*VTOLPOSE, "-q", "run", "--replay", str(flight), "--sensors", "imu,gps", "--speed", "0",
                                   "--mavlink", f"udpout:127.0.0.1:{port}"], env=_env(cache),
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            while time.perf_counter() - started < FIRST_POSE_TIMEOUT_S:
                try:
                    frame = udp.recv(65536)
                except socket.timeout:
                    if daemon.poll() is not None:
                        break
                    continue
                if frame[:1] == b"\xfd" and int.from_bytes(frame[7:10], "little") == ODOMETRY_ID:
                    return time.perf_counter() - started
            return float("inf")
        finally:
            daemon.terminate()
            daemon.wait()


def bench_cold_start(duration_s: float = 120.0) -> list[Row]:
    """First replay with an empty kernel cache against the second (target ≤ 1.5 ×), compile time, daemon's first pose."""
    from vtolpose.drivers.simulator import simulate_flight
    from vtolpose.drivers.simulator.export import write_flight

    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        flight = root / "book"
        write_flight(simulate_flight("book", duration_s, 1), flight)
        replay = ["-q", "replay", str(flight), "--sensors", "imu,gps", "--no-progress"]
        first = _timed(replay, root / "replay-cache")
        compiled_after = _wait_for_compiler(root / "replay-cache")
        second = _timed(replay, root / "replay-cache")
        rows.append(Row(f"first replay, empty kernel cache (book {duration_s:g} s)", first, "s wall",
                        "kernels interpreted; a background compiler started"))
        rows.append(Row("second replay, same cache", second, "s wall", f"its compiler finished {compiled_after:.1f} s "
                        "after the first replay"))
        rows.append(Row("first replay / second", first / second, "x", "", RATIO_TARGET))
        rows.append(Row("compiling every kernel (vtolpose warmup)", _timed(["-q", "warmup"], root / "warmup-cache"),
                        "s wall", "once per machine; in no speed figure"))
        cold = _first_odometry_s(flight, root / "daemon-cache")
        _wait_for_compiler(root / "daemon-cache")
        warm = _first_odometry_s(flight, root / "daemon-cache")
        rows.append(Row("daemon start to first ODOMETRY, empty cache", cold, "s",
                        "run --replay at full speed; kernels interpreted", FIRST_POSE_TARGET))
        rows.append(Row("daemon start to first ODOMETRY, warm cache", warm, "s", "", FIRST_POSE_TARGET))
        _wait_for_compiler(root / "daemon-cache")
    return rows
