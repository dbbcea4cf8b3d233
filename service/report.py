"""The JSON report of a replay: accuracy against truth, consistency, speed, and every count."""

from __future__ import annotations

from typing import Any

import numpy as np

from drivers.dataset import Dataset
from estimator.metrics import evaluate, gps_error_rmse, nees, nees_summary, pose_errors_for_nees
from service.replay import ReplayResult

REPORT_VERSION = 1


def build_report(result: ReplayResult, dataset: Dataset, cfg: dict[str, Any]) -> dict:
    est = result.estimator
    traj = result.trajectory
    report: dict[str, Any] = {
        "report_version": REPORT_VERSION,
        "dataset": dataset.meta["name"],
        "dataset_path": str(dataset.root),
        "variant": cfg["estimator.variant"],
        "sensor_set": result.sensors,
        "duration_s": round(result.duration_s, 6),
        "wall_s": round(result.wall_s, 6),
        "realtime_factor": round(result.duration_s / result.wall_s, 2) if result.wall_s > 0 else None,
        "estimates": int(len(traj.t_ns)),
        "initialised": est.initialized,
        "heading_aligned": est.heading_aligned,
        "heading_source": "in-motion alignment" if est.alignment is not None else "known" if est.heading_aligned else "unknown",
        "reset_counter": est.reset_counter,
        "sensors": est.counts_report(),
        "skipped_lines": dict(dataset.skipped),
        "events": [{"t_s": round((t - int(traj.t_ns[0])) * 1e-9, 3) if len(traj.t_ns) else None, "message": m} for t, m in est.events],
        "notes": list(result.notes),
    }
    if est.alignment is not None:
        a = est.alignment
        report["alignment"] = {
            "t_s": round((a.t_ns - int(traj.t_ns[0])) * 1e-9, 3) if len(traj.t_ns) else None,
            "sigma_roll_pitch_heading_deg": np.degrees(np.sqrt(np.diag(a.cov)[6:9])).tolist(),
            "residual_ratio": a.residual_ratio,
            "window_s": a.window_s,
            "fixes": a.n_fixes,
        }
    if est.state is not None:
        report["final_biases"] = {"gyro_rad_s": est.state.b_g.tolist(), "accel_m_s2": est.state.b_a.tolist()}
    truth = dataset.truth()
    if truth is None or len(traj.t_ns) < 2:
        report["truth"] = None
        return report
    point_b = dataset.calibration.truth_point_b
    scores = evaluate(traj.t_ns, traj.p, traj.q, truth, point_b)
    report["truth"] = "full" if truth.q is not None else "position only"
    report["position_rmse_m"] = scores["position_rmse_m"]
    if truth.q is not None:
        report["attitude_rmse_deg"] = scores["attitude_rmse_deg"]
    report["final_drift_m"] = scores["final_drift_m"]
    report["distance_travelled_m"] = scores["distance_travelled_m"]
    report["drift_percent"] = scores["drift_percent"]
    report["scores"] = scores
    gps = dataset.gps() if "gps" in result.sensors else None
    if gps is not None:
        gps_scores = gps_error_rmse(gps, truth, dataset.calibration.gps.lever_arm_b, point_b)
        report["gps_rmse_m"] = gps_scores["rmse_m"]
        report["gps_scores"] = gps_scores
        report["position_rmse_over_gps"] = report["position_rmse_m"] / gps_scores["rmse_m"]
    cov = result.covariances
    if len(cov.t_ns):
        err, c, dof = pose_errors_for_nees(cov.t_ns, cov.p, cov.q, cov.cov, truth, point_b)
        if len(err):
            values = nees(err, c)
            summary = nees_summary(values, dof)
            report["nees_mean"] = summary["nees_mean"]
            report["nees"] = summary
            report["nees_position_mean"] = float(np.mean(nees(err[:, :3], c[:, :3, :3])))
    return report


def summary_lines(report: dict) -> list[str]:
    """The few numbers a person looks at first."""
    def fmt(key: str, unit: str = "", scale: float = 1.0, digits: int = 4) -> str:
        value = report.get(key)
        return "n/a" if value is None else f"{value * scale:.{digits}f}{unit}"

    lines = [
        f"dataset {report['dataset']}  variant {report['variant']}  sensors {','.join(report['sensor_set'])}",
        f"  position RMSE {fmt('position_rmse_m', ' m')}   GPS RMSE {fmt('gps_rmse_m', ' m')}   ratio {fmt('position_rmse_over_gps', '', 1, 3)}",
        f"  attitude RMSE {fmt('attitude_rmse_deg', ' deg', 1, 3)}   final drift {fmt('final_drift_m', ' m')} ({fmt('drift_percent', ' %', 1, 2)} of {fmt('distance_travelled_m', ' m', 1, 1)})",
    ]
    if "nees" in report:
        n = report["nees"]
        lo, hi = n["band_per_sample"]
        verdict = "inside" if n["mean_in_band"] else "OUTSIDE"
        lines.append(f"  NEES mean {n['nees_mean']:.2f} ({n['dof']} dof; 95% band {lo:.2f}-{hi:.2f}: {verdict}; {100 * n['fraction_in_band']:.0f}% of samples in band)")
    lines.append(f"  {report['duration_s']:.1f} s of data in {report['wall_s']:.2f} s: {report['realtime_factor']}x real time")
    for name, c in report["sensors"].items():
        rej = ", ".join(f"{k} {v}" for k, v in c["rejected"].items()) or "none"
        lines.append(f"  {name}: {c['used']} used of {c['received']}; rejected: {rej}")
    return lines
