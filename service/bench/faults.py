"""Behaviour under injected faults, measured: the figures behind the fault table in docs/faults.md.

``fault-targets`` (the fault-tolerance targets, with the default SIFT features):
- landfill Test 3 (imu,camera,gps), 120 s, GPS off for 30 s from 60 s: how long after the GPS
  returns until the position error is back within 2 × the fault-free run's RMSE;
- book Test 3, 90 s, camera off for 30 s from 40 s: NEES over the outage against its 95 % band;
- a 20 m GPS jump (1 s of fixes) in both: fixes rejected and counted, largest deviation of the
  trajectory from the fault-free run's.
``fault-table``: every fault kind on a landfill IMU+GPS flight, the camera faults on a book Test 3 (ORB) flight: the table.

Every replay goes through the runtime exactly as ``vtolpose replay --fault`` does; a trace of
the fused poses (time, position, quality, reset counter) is kept alongside the report.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.estimator import (
    chi2_band, interpolate_poses, nees, nees_summary, OutputPose, pose_errors_for_nees, quat_to_rot,
)
from vtolpose.service.replay.faults import parse_faults
from vtolpose.service.replay.session import ReplayResult, replay
from vtolpose.service.replay.report import scoring_times
from vtolpose.service.runtime.status import pose_quality
from vtolpose.service.bench.rows import Row



@dataclass
class FaultTrace:
    """Every fused pose of a replay: what the outputs would have said about it."""

    t_ns: list[int] = field(default_factory=list)
    p: list[np.ndarray] = field(default_factory=list)
    q: list[np.ndarray] = field(default_factory=list)
    quality: list[int] = field(default_factory=list)
    resets: list[int] = field(default_factory=list)

    def record(self, pose: OutputPose) -> None:
        self.t_ns.append(pose.t_ns)
        self.p.append(pose.p)
        self.q.append(pose.q)
        self.quality.append(pose_quality(pose))
        self.resets.append(pose.reset_counter)


@dataclass
class FaultRun:
    """A replay with its faults, its trace, and the errors against truth on the data clock."""

    result: ReplayResult
    trace: FaultTrace
    t_s: np.ndarray  # data seconds from the first sample (clock steps undone)
    error_m: np.ndarray  # position error of the truth point at each fused pose
    quality: np.ndarray
    resets: np.ndarray

    def between(self, t0_s: float, t1_s: float) -> np.ndarray:
        return (self.t_s >= t0_s) & (self.t_s < t1_s)

    def rmse(self, t0_s: float = 0.0, t1_s: float = np.inf) -> float:
        m = self.between(t0_s, t1_s)
        return float(np.sqrt(np.mean(self.error_m[m] ** 2))) if np.any(m) else float("nan")


def traced_replay(dataset: Dataset, cfg: dict[str, Any], sensors: Sequence[str], faults: Sequence[str] = (),
                  seed: int = 0) -> FaultRun:
    """``vtolpose replay --fault ...`` with a trace of every fused pose and its error against truth."""
    trace = FaultTrace()
    result = replay(dataset, cfg, list(sensors), faults=parse_faults(faults), fault_seed=seed, on_fused=trace.record)
    truth = dataset.truth()
    t_ns = np.array(trace.t_ns, dtype=np.int64)
    t_data = scoring_times(result, t_ns)
    t_first = int(dataset.imu().t_ns[0])
    inside = (t_data >= truth.t_ns[0]) & (t_data <= truth.t_ns[-1])
    p, q = np.array(trace.p)[inside], np.array(trace.q)[inside]
    p_true, _ = interpolate_poses(t_data[inside], truth.t_ns, truth.p, truth.q)
    error = np.linalg.norm(p_true - (p + quat_to_rot(q) @ dataset.calibration.truth_point_b), axis=1)
    return FaultRun(result, trace, (t_data[inside] - t_first) * 1e-9, error,
                    np.array(trace.quality)[inside], np.array(trace.resets)[inside])


def recovery_time_s(run: FaultRun, t_from_s: float, threshold_m: float, hold_s: float = 5.0) -> float:
    """Seconds after ``t_from_s`` until the 1-s running RMS position error is within ``threshold_m``
    and stays there for ``hold_s`` (inf if it never does)."""
    m = run.t_s >= t_from_s
    t, e = run.t_s[m], run.error_m[m]
    if t.size == 0:
        return float("inf")
    bins = np.floor((t - t_from_s) * 10.0).astype(int)  # 0.1 s bins, 1-s running RMS over 10 of them
    sums = np.bincount(bins, e * e)
    counts = np.maximum(np.bincount(bins), 1)
    rms = np.sqrt(np.convolve(sums, np.ones(10), "full")[: sums.size] / np.convolve(counts, np.ones(10), "full")[: sums.size])
    good = rms <= threshold_m
    need = int(round(hold_s * 10.0))
    for k in range(good.size - need + 1):
        if good[k:k + need].all():
            return k / 10.0
    return float("inf")


def window_nees(run: FaultRun, dataset: Dataset, t0_s: float, t1_s: float) -> dict[str, float]:
    """NEES of the pose samples inside a data-time window, against the per-sample 95 % band."""
    cov = run.result.covariances
    t_data = scoring_times(run.result, cov.t_ns)
    t_first = int(dataset.imu().t_ns[0])
    m = ((t_data - t_first) * 1e-9 >= t0_s) & ((t_data - t_first) * 1e-9 < t1_s)
    err, c, dof = pose_errors_for_nees(t_data[m], cov.p[m], cov.q[m], cov.cov[m], dataset.truth(),
                                       dataset.calibration.truth_point_b)
    summary = nees_summary(nees(err, c), dof)
    lo, hi = summary["band_per_sample"]
    mean_lo, mean_hi = chi2_band(dof, n_samples=summary["samples"])
    return {"mean": summary["nees_mean"], "fraction_in_band": summary["fraction_in_band"], "band_lo": lo, "band_hi": hi,
            "mean_band_lo": mean_lo, "mean_band_hi": mean_hi, "samples": summary["samples"], "dof": dof}


def trajectory_deviation_m(run: FaultRun, clean: FaultRun, skip_t_ns: np.ndarray | None = None) -> float:
    """Largest distance between two runs' fused positions, ``clean`` interpolated at ``run``'s stamps.

    The stamps need not match: a measurement splits the filter's IMU chunks at its own time, so
    a run that received a fix the other did not publishes at slightly different instants. A stamp
    published twice (a pose at a fix's time, then the IMU sample at that time) counts with its last
    pose. ``skip_t_ns``: stamps of measurements (GPS fixes) — the pose at such a stamp is before or
    after that measurement's update depending on which arrived first, so it is left out.
    """

    def last_per_stamp(trace: FaultTrace) -> tuple[np.ndarray, np.ndarray]:
        t = np.array(trace.t_ns, dtype=np.int64)
        last = np.flatnonzero(np.append(t[1:] != t[:-1], True))
        return t[last], np.array(trace.p)[last]

    ta, pa = last_per_stamp(run.trace)
    tb, pb = last_per_stamp(clean.trace)
    inside = (ta >= tb[0]) & (ta <= tb[-1]) if tb.size else np.zeros(ta.size, bool)
    if skip_t_ns is not None:
        inside &= ~np.isin(ta, skip_t_ns)
    if not np.any(inside):
        return float("nan")
    x = (ta[inside] - tb[0]) * 1e-9
    xb = (tb - tb[0]) * 1e-9
    pb_at = np.column_stack([np.interp(x, xb, pb[:, k]) for k in range(3)])
    return float(np.max(np.linalg.norm(pa[inside] - pb_at, axis=1)))


def _dataset(tmp: Path, scenario: str, duration_s: float, camera: bool) -> Dataset:
    from vtolpose.drivers.simulator.render import default_camera

    root = tmp / f"{scenario}{int(duration_s)}"
    write_flight(simulate_flight(scenario, duration_s, 1), root, camera=default_camera() if camera else None)
    return Dataset.open(root)


def jump_rows(name: str, dataset: Dataset, cfg: dict[str, Any], sensors: Sequence[str], clean: FaultRun,
              start_s: float) -> list[Row]:
    """A 20 m jump of 1 s of fixes from ``start_s``: how many were rejected, and how far the trajectory
    moved — from the fault-free run, and from a run where those fixes are simply missing (the jump's
    own effect: a rejected fix must leave the estimate as if it never came)."""
    jump = traced_replay(dataset, cfg, sensors, [f"gps-jump:{start_s:g}:20,0,0"])
    missing = traced_replay(dataset, cfg, sensors, [f"gps-off:{start_s:g}:1"])
    gate = lambda run: run.result.estimator.status().counts["gps"]["rejected"].get("chi2_gate", 0)  # noqa: E731
    jumped = jump.result.faults.report()[0]["samples_affected"]
    fixes = dataset.gps().t_ns
    return [
        (f"{name} gps-jump:{start_s:g}:20,0,0: fixes rejected by the gate", float(gate(jump) - gate(missing)), "fixes",
         f"of {jumped} jumped (beyond the rejections of the run without them)"),
        (f"{name} gps-jump: deviation from the same fixes missing", 100.0 * trajectory_deviation_m(jump, missing, fixes), "cm",
         "target <= 1 cm"),
        (f"{name} gps-jump: deviation from the fault-free run", 100.0 * trajectory_deviation_m(jump, clean, fixes), "cm",
         "what losing those fixes costs"),
    ]


def bench_fault_targets() -> list[Row]:
    """GPS back after a 30 s loss, NEES through a 30 s camera loss, a 20 m GPS jump: Test 3, SIFT, vs fault-free runs."""
    rows: list[Row] = []
    cfg = load_config()
    test3 = ["imu", "camera", "gps"]
    with tempfile.TemporaryDirectory() as tmp:
        landfill = _dataset(Path(tmp), "landfill", 120.0, camera=True)
        clean = traced_replay(landfill, cfg, test3)
        ss = clean.rmse(20.0)
        lost = traced_replay(landfill, cfg, test3, ["gps-off:60:30"])
        rec = recovery_time_s(lost, 90.0, 2.0 * ss)
        rows += [
            ("landfill T3: steady-state position RMSE (no fault)", ss, "m", "from 20 s on"),
            ("landfill T3 gps-off:60:30: largest error in the outage", float(lost.error_m[lost.between(60, 90)].max()), "m",
             f"quality min {int(lost.quality[lost.between(61, 90)].min())}"),
            ("landfill T3 gps-off:60:30: back within 2x RMSE after", rec, "s", "target <= 10 s (1-s RMS, held 5 s)"),
            ("landfill T3 gps-off:60:30: largest error 10-20 s after", float(lost.error_m[lost.between(100, 110)].max()), "m",
             f"2x RMSE = {2 * ss:.3f} m"),
        ]
        n = window_nees(lost, landfill, 60.0, 90.0)
        rows.append(("landfill T3 gps-off:60:30: NEES mean in the outage", n["mean"], "",
                     f"{n['dof']} dof; {100 * n['fraction_in_band']:.0f}% of samples in the 95% band"))
        rows += jump_rows("landfill T3", landfill, cfg, test3, clean, 60.0)
        book = _dataset(Path(tmp), "book", 90.0, camera=True)
        clean = traced_replay(book, cfg, test3)
        dark = traced_replay(book, cfg, test3, ["camera-off:40:30"])
        n = window_nees(dark, book, 40.0, 70.0)
        base = window_nees(clean, book, 40.0, 70.0)
        rows += [
            ("book T3 camera-off:40:30: NEES mean in the outage", n["mean"], "",
             f"{n['dof']} dof; band of the mean {n['mean_band_lo']:.2f}-{n['mean_band_hi']:.2f}; "
             f"no fault: {base['mean']:.2f}"),
            ("book T3 camera-off:40:30: NEES samples inside the band", 100.0 * n["fraction_in_band"], "%",
             f"{n['samples']} samples; per-sample 95% band {n['band_lo']:.2f}-{n['band_hi']:.2f}; "
             f"no fault: {100 * base['fraction_in_band']:.0f}%"),
            ("book T3 camera-off:40:30: largest error in the outage", float(dark.error_m[dark.between(40, 70)].max()), "m",
             f"no fault: {float(clean.error_m[clean.between(40, 70)].max()):.4f} m"),
        ]
        rows += jump_rows("book T3", book, cfg, test3, clean, 40.0)
    return rows


TABLE_FAULTS = (
    "gps-off:45:30", "imu-gap:45:0.5", "imu-gap:45:2", "gps-jump:45:20,0,0", "gps-jump:45:20,0,0:10",
    "gps-multipath:45:30:10:0.3", "clock-step:45:+2.0", "clock-step:45:-2.0", "nan:imu:45:0.5", "nan:gps:45:5",
)
CAMERA_TABLE_FAULTS = ("camera-off:12:6", "camera-freeze:12:3")


def fault_row(run: FaultRun, clean: FaultRun, fault: str, fixes_t_ns: np.ndarray) -> dict[str, Any]:
    """What one fault did, in the table's terms (data seconds from the first sample)."""
    f = parse_faults([fault])[0]
    start = f.start_s
    end = start + (f.duration_s if np.isfinite(f.duration_s) else 0.0)
    ss = clean.rmse(20.0)
    before = run.between(start - 5.0, start)
    status = run.result.estimator.status()
    return {
        "fault": fault,
        "max_error_m": float(run.error_m[run.between(start, end + 10.0)].max()),
        "clean_max_error_m": float(clean.error_m[clean.between(start, end + 10.0)].max()),
        "quality_before": int(np.median(run.quality[before])),
        "quality_min": int(run.quality[run.between(start, end + 10.0)].min()),
        "quality_after": int(np.median(run.quality[run.between(end + 8.0, end + 10.0)])),
        "recovery_s": recovery_time_s(run, end, 2.0 * ss),
        "resets": dict(status.health["resets"]),
        "counted": {k: {**v["rejected"], **v.get("flagged", {})} for k, v in status.counts.items()
                    if k in ("imu", "gps", "camera")},
        "late": {k: v["rejected"] for k, v in run.result.fusion_counts.items()},
        "deviation_cm": 100.0 * trajectory_deviation_m(run, clean, fixes_t_ns),
    }


def _table(name: str, dataset: Dataset, cfg: dict[str, Any], sensors: Sequence[str], faults: Sequence[str]) -> list[Row]:
    clean = traced_replay(dataset, cfg, sensors)
    base = {k: {**v["rejected"], **v.get("flagged", {})} for k, v in clean.result.estimator.status().counts.items()}
    rows: list[Row] = [(f"{name}: RMSE without faults", clean.rmse(20.0), "m", f"from 20 s on; counted {base}")]
    for fault in faults:
        r = fault_row(traced_replay(dataset, cfg, sensors, [fault]), clean, fault, dataset.gps().t_ns)
        rows.append((f"{fault}: largest error (fault + 10 s)", r["max_error_m"], "m",
                     f"no fault {r['clean_max_error_m']:.3f}; quality {r['quality_before']} -> min {r['quality_min']} -> "
                     f"{r['quality_after']}; back within 2x RMSE {r['recovery_s']:.1f} s after; resets {r['resets'] or 0}; "
                     f"counted {r['counted']}{'; late ' + str(r['late']) if r['late'] else ''}"))
    return rows


def bench_fault_table() -> list[Row]:
    """Each fault kind: largest error, quality, recovery, resets, counts (the figures behind the table in docs/faults.md)."""
    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as tmp:
        landfill = _dataset(Path(tmp), "landfill", 100.0, camera=False)
        rows += _table("landfill imu,gps 100 s", landfill, load_config(), ["imu", "gps"], TABLE_FAULTS)
        book = _dataset(Path(tmp), "book", 30.0, camera=True)
        cfg = load_config(None, {"features": {"detector": "orb"}})
        rows += _table("book imu,camera,gps 30 s (ORB)", book, cfg, ["imu", "camera", "gps"], CAMERA_TABLE_FAULTS)
    return rows
