"""Smoothing benchmarks: accuracy of filtered, smoothed and fixed-lag poses, and what smoothing costs.

The real flights are in ``euroc`` (``vtolpose.service.bench.euroc``: its table has the smoothed and
fixed-lag columns). ``smoothing-sim``: simulated book and landfill flights, Test 1 (IMU+GPS) and
Test 3 (IMU+camera+GPS), replayed with ``--smooth`` and scored from 15 s: the three kinds side by
side, and the backward pass against the replay's wall time. ``smoothing-landmarks``: the
robot-block smoother against the exact full-state one on a book Test 3 flight (how much the
marginalised landmarks cost). ``smoothing-hour``: resident memory of ``replay --smooth`` over a
simulated hour. ``smoothing-latency``: the daemon's pose latency with the fixed-lag smoother on
and off, in the same run.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.drivers.simulator.render import default_camera
from vtolpose.estimator import evaluate, FullStateRecorder, smooth_steps
from vtolpose.service.bench.rows import Row
from vtolpose.service.bench.runtime import latency_run
from vtolpose.service.replay.report import build_report
from vtolpose.service.replay.session import replay
from vtolpose.service.replay.smoothing import replay_smoothed
from vtolpose.service.runtime.step_taps import SmoothingPlan

SCORE_FROM_S = 15.0


def _kind_rows(label: str, report: dict, targets: dict[str, str], plain_wall_s: float | None = None) -> list[Row]:
    """Position / GPS, attitude and NEES of each kind; the smoothed-over-filtered ratio; the cost."""
    sm = report["smoothing"]
    rows = []
    for kind in ("filtered", "smoothed", "fixed_lag"):
        k = sm.get(kind)
        if k is None:
            continue
        name = f"{label} {kind.replace('_', '-')}"
        if "position_rmse_over_gps" in k:
            rows.append(Row(f"{name} position / GPS RMSE", k["position_rmse_over_gps"], "x",
                            f"{k['position_rmse_m']:.4f} m", targets.get(f"{kind} position")))
        else:
            rows.append(Row(f"{name} position RMSE", k["position_rmse_m"], "m", "", None))
        if k.get("attitude_rmse_deg") is not None:
            rows.append(Row(f"{name} attitude RMSE", k["attitude_rmse_deg"], "deg", "", targets.get(f"{kind} attitude")))
        if "nees" in k:
            lo, hi = k["nees"]["band_per_sample"]
            rows.append(Row(f"{name} NEES mean", k["nees_mean"], f"({k['nees']['dof']} dof)", f"band {lo:.2f}-{hi:.2f}"))
    rows.append(Row(f"{label} smoothed / filtered position", sm["smoothed_over_filtered"], "x", "",
                    targets.get("smoothed/filtered")))
    if plain_wall_s is not None:
        rows.append(Row(f"{label} backward pass / plain replay wall time", sm["backward_s"] / plain_wall_s, "x",
                        f"{sm['backward_s']:.2f} s after a {plain_wall_s:.2f} s replay; {sm['steps']} steps, "
                        f"{sm['segments']} segment(s); replay --smooth took {report['wall_s']:.2f} s", "<= 0.5"))
    else:
        rows.append(Row(f"{label} backward pass / replay wall time", sm["backward_over_replay"], "x",
                        f"{sm['backward_s']:.2f} s; {sm['steps']} steps, {sm['segments']} segment(s)", "<= 0.5"))
    return rows


def _smoothed_report(dataset: Dataset, sensors: list[str], overrides: dict | None = None) -> dict:
    cfg = load_config(None, overrides or {})
    result = replay_smoothed(dataset, cfg, sensors=sensors)
    return build_report(result, dataset, cfg, SCORE_FROM_S)


SIM_TARGETS = {"smoothed/filtered": "<= 0.7"}


def bench_smoothing_sim(scenarios: tuple[tuple[str, float], ...] = (("book", 120.0), ("landfill", 300.0))) -> list[Row]:
    """Simulated Test 1 and Test 3 with --smooth from 15 s (target: smoothed ≤ 0.7 × filtered)."""
    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as tmp:
        for scenario, duration in scenarios:
            path = Path(tmp) / scenario
            write_flight(simulate_flight(scenario, duration, 1), path, camera=default_camera())
            dataset = Dataset.open(path)
            for test, sensors in (("Test 1", ["imu", "gps"]), ("Test 3", ["imu", "camera", "gps"])):
                report = _smoothed_report(dataset, sensors)
                rows += _kind_rows(f"{scenario} {duration:g} s {test}", report, SIM_TARGETS)
    return rows


def bench_smoothing_landmarks(duration_s: float = 40.0) -> list[Row]:
    """Book Test 3: the robot-block smoother against the exact full-state one (landmarks kept)."""
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "book"
        flight = simulate_flight("book", duration_s, 1)
        write_flight(flight, root, camera=default_camera())
        dataset = Dataset.open(root)
        steps: list = []
        held: dict = {}

        full = FullStateRecorder(lambda: held["est"].map_ids())  # the map's ids, from the estimator once it exists

        def prepare(runtime) -> None:
            held["est"] = runtime.est

        t0 = time.perf_counter()
        cfg = load_config(None, {"estimator": {"camera": {"estimate_time_offset": False}}})  # the pass has no such state
        result = replay(dataset, cfg, ["imu", "camera", "gps"], prepare=prepare,
                        smoothing=SmoothingPlan(step_sink=steps.append, beside=full))
        wall = time.perf_counter() - t0
    block = smooth_steps(steps)
    t_full, x_full = full.smooth()
    start = int(flight.imu.t_ns[0] + SCORE_FROM_S * 1e9)
    traj = result.trajectory

    def score(t: np.ndarray, p: np.ndarray, q: np.ndarray) -> dict:
        keep = t >= start
        return evaluate(t[keep], p[keep], q[keep], flight.truth)

    f, b, x = score(traj.t_ns, traj.p, traj.q), score(block.t_ns, block.p, block.q), score(t_full, x_full[:, 0:3], x_full[:, 6:10])
    common = np.intersect1d(block.t_ns[block.t_ns >= start], t_full)
    gap = x_full[np.searchsorted(t_full, common), 0:3] - block.p[np.searchsorted(block.t_ns, common)]
    landmarks = max((r.n_landmarks for r in result.frames), default=0)
    return [
        Row("book Test 3 filtered position RMSE", f["position_rmse_m"], "m", f"attitude {f['attitude_rmse_deg']:.3f} deg"),
        Row("book Test 3 robot-block smoothed position RMSE", b["position_rmse_m"], "m",
            f"attitude {b['attitude_rmse_deg']:.3f} deg; {b['position_rmse_m'] / f['position_rmse_m']:.2f} x filtered"),
        Row("book Test 3 full-state smoothed position RMSE", x["position_rmse_m"], "m",
            f"attitude {x['attitude_rmse_deg']:.3f} deg; {x['position_rmse_m'] / f['position_rmse_m']:.2f} x filtered"),
        Row("robot-block minus full-state smoothed position, RMS", float(np.sqrt(np.mean(np.sum(gap**2, axis=1)))), "m",
            f"max {np.max(np.linalg.norm(gap, axis=1)):.4f} m; up to {landmarks} landmarks; {duration_s:g} s, "
            f"replay with the full-state recorder {wall:.0f} s"),
    ]


def _replay_peak(args: list[str]) -> tuple[float, dict]:
    """Run ``vtolpose replay ARGS --report R`` in its own process: its peak resident memory [MB] and its report."""
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "r.json"
        proc = subprocess.Popen([sys.executable, "-m", "vtolpose", "replay", *args, "--no-progress", "-q",
                                 "--report", str(report)], stdout=subprocess.DEVNULL)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        if proc.returncode != 0:
            raise RuntimeError(f"vtolpose replay {' '.join(args)} failed with status {proc.returncode}")
        return usage.ru_maxrss / 1024.0, json.loads(report.read_text())


def bench_smoothing_hour(duration_s: float = 3600.0) -> list[Row]:
    """One hour of IMU+GPS (landfill): peak memory of replay and of replay --smooth, each in its own process."""
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "hour"
        write_flight(simulate_flight("landfill", duration_s, 1), root)
        base = [str(root), "--sensors", "imu,gps"]
        plain_mb, plain = _replay_peak(base)
        smooth_mb, smoothed = _replay_peak(base + ["--smooth", "--out", str(Path(tmp) / "s.txt"),
                                                  "--set", f"smoothing.temp_dir={tmp}"])
    sm = smoothed["smoothing"]
    return [
        Row(f"{duration_s / 60:.0f}-minute replay, peak resident memory", plain_mb, "MB",
            f"{plain['wall_s']:.0f} s wall, {plain['estimates']} filtered poses kept for the report"),
        Row(f"{duration_s / 60:.0f}-minute replay --smooth, peak resident memory", smooth_mb, "MB",
            f"{smooth_mb - plain_mb:+.0f} MB; forward record {sm['disk_mb']:.0f} MB on disk for {sm['steps']} steps"),
        Row("replay --smooth wall time / plain replay", smoothed["wall_s"] / plain["wall_s"], "x",
            f"{smoothed['wall_s']:.0f} s: recording the steps and running the fixed-lag smoother"),
        Row("backward pass / plain replay wall time", sm["backward_s"] / plain["wall_s"], "x",
            f"{sm['backward_s']:.1f} s", "<= 0.5"),
    ]


def bench_smoothing_latency(duration_s: float = 15.0) -> list[Row]:
    """Pose latency (IMU in → MAVLink and Zenoh out) with the live fixed-lag smoother on, then off."""
    rows = latency_run(duration_s, None, "fixed lag 2 s")
    rows += latency_run(duration_s, None, "smoothing off", {"smoothing": {"fixed_lag_s": 0.0}})
    return rows
