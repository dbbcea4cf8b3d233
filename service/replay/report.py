"""The JSON report of a replay: accuracy against truth, consistency, speed, and every count."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from vtolpose.drivers.files.dataset import Dataset
from vtolpose.estimator import (
    evaluate, gps_error_rmse, interpolate_poses, nees, nees_summary, pose_errors_for_nees, quat_mul, quat_to_rot,
    rot_to_quat, so3_exp, so3_log, yaw_of,
)
from vtolpose.drivers.files.series import TruthSeries
from vtolpose.service.replay.session import CovarianceSamples, ReplayResult, Trajectory
from vtolpose.service.runtime.wiring import estimator_variant

REPORT_VERSION = 1


def build_report(result: ReplayResult, dataset: Dataset, cfg: dict[str, Any], score_from_s: float = 0.0) -> dict:
    """The report of a replay; ``score_from_s``: accuracy from this long after the truth starts."""
    status = result.estimator.status()
    traj = result.trajectory
    report: dict[str, Any] = {
        "report_version": REPORT_VERSION,
        "dataset": dataset.meta["name"],
        "dataset_path": str(dataset.root),
        "variant": estimator_variant(cfg),
        "sensor_set": result.sensors,
        "duration_s": round(result.duration_s, 6),
        "wall_s": round(result.wall_s, 6),
        "realtime_factor": round(result.duration_s / result.wall_s, 2) if result.wall_s > 0 else None,
        "kernels": result.kernels.describe() if result.kernels is not None else None,
        "estimates": int(len(traj.t_ns)),
        "initialised": status.initialised,
        "heading_aligned": status.heading_aligned,
        "heading_source": status.heading_source,
        "mode": status.mode.value,
        "reset_counter": status.reset_counter,
        "sensors": {name: dict(counts) for name, counts in status.counts.items()},
        "skipped_lines": dict(dataset.skipped),
        "clock_steps": {rel: [step.describe() for step in steps] for rel, steps in dataset.clock_steps.items()},
        "gps_noise": dict(status.gps_noise),
        "events": [{"t_s": round((e.t_ns - result.data_t0_ns) * 1e-9, 3), "message": e.message} for e in status.events],
        "notes": list(result.notes),
    }
    if result.faults is not None:
        report["faults"] = result.faults.report()
    if result.health:
        report["health"] = result.health
    if result.failures:
        report["failures"] = result.failures
    if status.heading_placement is not None:
        placed = dataclasses.asdict(status.heading_placement)
        t_placed = placed.pop("t_ns")
        report["heading_placement"] = {"t_s": round((t_placed - result.data_t0_ns) * 1e-9, 3), **placed}
    if status.gyro_bias is not None:
        report["final_biases"] = {"gyro_rad_s": list(status.gyro_bias), "accel_m_s2": list(status.accel_bias)}
    camera = camera_summary(result)
    if camera is not None:
        report["camera"] = camera
    waited = visual_start_report(result)
    if waited is not None:
        report["visual_start"] = waited
    truth = dataset.truth()
    if truth is None or len(traj.t_ns) < 2:
        report["truth"] = None
        report["no_scores"] = ("the dataset has no truth: nothing to score against" if truth is None
                               else "fewer than two poses: nothing to score")
        return report
    point_b = dataset.calibration.truth_point_b
    valid = traj.valid
    if not np.any(valid):
        report["truth"] = None
        report["never_valid"] = "no pose could be scored: every one came before the position"
        report["no_scores"] = report["never_valid"]
        return report
    if not np.all(valid):
        first = int(np.argmax(valid))
        report["first_scored_s"] = round((int(traj.t_ns[first]) - int(traj.t_ns[0])) * 1e-9, 3)
    align = start_alignment(result, truth, point_b)
    if align is not None:
        report["position_reference"] = {
            "kind": "start",
            "note": "no absolute position in this sensor set: the estimate's origin is where it started (and, for a "
                    "visual-inertial start, its heading its own), so it is moved onto the truth at its first valid "
                    "pose before scoring",
            "offset_m": (align.target - align.pivot).tolist(),
            "heading_deg": float(np.degrees(so3_log(align.rotation)[2])),
            "heading_aligned": align.heading_aligned,
        }
        if align.heading_aligned:
            report["position_reference"]["heading_note"] = (
                "a camera-only frame cannot know the world's heading: it is turned onto the truth's at that pose, "
                "and the NEES covers what the frame can know (the pose relative to its start: position and tilt, 5 dof), its "
                "covariance the filter's in its own frame less the origin's variance at the start (a gauge the shift takes "
                "off the errors); the heading's gauge cannot be taken off the filter's covariance, so the heading is "
                "left out of the NEES and its drift counts in the attitude's RMSE only")
    align = align or StartAlignment(np.eye(3), np.zeros(3), np.zeros(3), False)
    if score_from_s > 0.0:
        truth = truth_from(truth, int(truth.t_ns[0] + round(score_from_s * 1e9)))
        report["score_from_s"] = score_from_s
    report["truth"] = "full" if truth.q is not None else "position only"
    gps = dataset.gps() if "gps" in result.sensors else None
    gps_scores = gps_error_rmse(gps, truth, dataset.calibration.gps.lever_arm_b, point_b) if gps is not None else None
    filtered = accuracy(result, truth, point_b, align, traj, result.covariances, gps_scores)
    report["position_rmse_m"] = filtered["position_rmse_m"]
    if truth.q is not None:
        report["attitude_rmse_deg"] = filtered["attitude_rmse_deg"]
        if status.heading_placement is not None:  # before it the outputs said the heading was unknown
            t_data = scoring_times(result, traj.t_ns[valid])
            placed = t_data >= status.heading_placement.t_ns
            if np.count_nonzero(placed) >= 2:
                report["attitude_rmse_with_heading_deg"] = evaluate(
                    t_data[placed], align.points(traj.p[valid][placed]), align.attitudes(traj.q[valid][placed]), truth,
                    point_b)["attitude_rmse_deg"]
    scores = filtered["scores"]
    report["final_drift_m"] = scores["final_drift_m"]
    report["distance_travelled_m"] = scores["distance_travelled_m"]
    report["drift_percent"] = scores["drift_percent"]
    report["scores"] = scores
    if gps_scores is not None:
        report["gps_rmse_m"] = gps_scores["rmse_m"]
        report["gps_scores"] = gps_scores
        report["position_rmse_over_gps"] = filtered["position_rmse_over_gps"]
    for key in ("nees_mean", "nees", "nees_position_mean"):
        if key in filtered:
            report[key] = filtered[key]
    if result.smoothing is not None:
        report["smoothing"] = smoothing_report(result, truth, point_b, align, gps_scores, filtered)
    return report


def truth_from(truth: TruthSeries, t0_ns: int) -> TruthSeries:
    """The truth from ``t0_ns`` on: scores then cover only that stretch (e.g. after the start-up)."""
    keep = truth.t_ns >= t0_ns
    if not np.any(keep):
        raise ValueError(f"the truth ends before the scoring start (t_ns={t0_ns})")
    pick = lambda a: None if a is None else a[keep]  # noqa: E731
    return TruthSeries(truth.t_ns[keep], truth.p[keep], pick(truth.q), pick(truth.v), pick(truth.bias_g), pick(truth.bias_a))


def accuracy(result: ReplayResult, truth: TruthSeries, point_b: np.ndarray, align: StartAlignment, traj: Trajectory,
             cov: CovarianceSamples, gps_scores: dict | None) -> dict:
    """Position/attitude RMSE, ratio to the GPS and NEES of one trajectory (filtered, smoothed, fixed-lag);
    poses marked not to be used are left out."""
    valid = traj.valid
    scores = evaluate(scoring_times(result, traj.t_ns[valid]), align.points(traj.p[valid]), align.attitudes(traj.q[valid]),
                      truth, point_b)
    out: dict[str, Any] = {"position_rmse_m": scores["position_rmse_m"], "attitude_rmse_deg": scores["attitude_rmse_deg"],
                           "scores": scores}
    if gps_scores is not None:
        out["position_rmse_over_gps"] = scores["position_rmse_m"] / gps_scores["rmse_m"]
    if align.gauge is not None:  # the pose since the start: samples after it, their covariance less the gauge
        cov = relative_samples(cov, align)
    if len(cov.t_ns):
        err, c, dof = pose_errors_for_nees(scoring_times(result, cov.t_ns), align.points(cov.p), align.attitudes(cov.q),
                                           align.covariances(cov.cov), truth, point_b)
        if len(err):
            if align.heading_aligned and dof == 6:
                # The turn put the start's heading on the truth's: the frame's heading is a gauge the run never learns,
                # held in the filter's covariance with the map's, so it is marginalised out (what is scored is the
                # position and the tilt; the heading's drift still counts in the attitude's RMSE).
                err, c, dof = err[:, :5], c[:, :5, :5], 5
            values = nees(err, c)
            summary = nees_summary(values, dof)
            out["nees_mean"] = summary["nees_mean"]
            out["nees"] = summary
            out["nees_position_mean"] = float(np.mean(nees(err[:, :3], c[:, :3, :3])))
    return out


def relative_samples(cov: CovarianceSamples, align: StartAlignment) -> CovarianceSamples:
    """The samples after the start alignment's pose (there the errors are zero by construction), with the
    covariance of the position since then (:meth:`StartAlignment.relative`)."""
    after = cov.t_ns > align.pivot_t_ns
    return CovarianceSamples(cov.t_ns[after], cov.p[after], cov.q[after], align.relative(cov.cov[after]))


def smoothing_report(result: ReplayResult, truth: TruthSeries, point_b: np.ndarray, align: StartAlignment,
                     gps_scores: dict | None, filtered: dict) -> dict:
    """Filtered, smoothed and fixed-lag scores side by side, and what the backward pass cost."""
    sm = result.smoothing
    table = {"filtered": filtered, "smoothed": accuracy(result, truth, point_b, align, sm.smoothed, sm.smoothed_cov, gps_scores)}
    if len(sm.fixed_lag.t_ns) >= 2:
        table["fixed_lag"] = accuracy(result, truth, point_b, align, sm.fixed_lag, sm.fixed_lag_cov, gps_scores)
    keys = ("position_rmse_m", "attitude_rmse_deg", "position_rmse_over_gps", "nees_mean", "nees_position_mean")
    out: dict[str, Any] = {kind: {k: v[k] for k in keys if k in v} for kind, v in table.items()}
    for kind, v in table.items():
        if "nees" in v:
            out[kind]["nees"] = v["nees"]
    out["smoothed_over_filtered"] = table["smoothed"]["position_rmse_m"] / filtered["position_rmse_m"]
    out.update(lag_s=sm.lag_s, steps=sm.steps, segments=sm.segments, backward_s=round(sm.backward_s, 3),
               backward_over_replay=round(sm.backward_s / result.wall_s, 3) if result.wall_s > 0 else None,
               disk_mb=round(sm.disk_bytes / 1e6, 1), fixed_lag_dropped=sm.fixed_lag_dropped)
    return out


def scoring_times(result: ReplayResult, t_ns: np.ndarray) -> np.ndarray:
    """The estimates' stamps on the truth's clock: an injected clock step is undone before scoring."""
    return result.faults.source_time_ns(t_ns) if result.faults is not None else t_ns


@dataclass(frozen=True, slots=True)
class StartAlignment:
    """Moves an estimate made in a frame of its own onto the truth: a turn about world down through
    ``pivot`` (the estimate's tracked point at its first valid pose) and a shift of it onto ``target``."""

    rotation: np.ndarray
    pivot: np.ndarray
    target: np.ndarray
    heading_aligned: bool  # the turn takes off a heading the estimate's frame could not know
    # What the shift takes off the errors, as the filter's covariance holds it: the origin's variance at its start
    # (3 × 3), a gauge no measurement of such a run informs; None: nothing taken off.
    gauge: np.ndarray | None = None
    pivot_t_ns: int = 0

    def points(self, p: np.ndarray) -> np.ndarray:
        return self.target + (np.asarray(p) - self.pivot) @ self.rotation.T

    def attitudes(self, q: np.ndarray) -> np.ndarray:
        return quat_mul(np.broadcast_to(rot_to_quat(self.rotation), np.shape(q)), q)

    def covariances(self, cov: np.ndarray) -> np.ndarray:
        """6 × 6 [δp, δθ] covariances (world frame) seen in the moved frame."""
        J = np.zeros((6, 6))
        J[0:3, 0:3] = J[3:6, 3:6] = self.rotation
        return J @ cov @ J.T

    def relative(self, cov: np.ndarray) -> np.ndarray:
        """``cov`` less the gauge: the errors scored are the position's since the start, where the shift makes
        them zero, so their covariance is the filter's less the origin's variance it held there. That part is
        exact: a shift of everything is invisible to every measurement and the propagation alike, so the start's
        independent origin variance stays as it was, added to the rest (OC-EKF keeps the camera's update blind
        to it). Without this a frame's 2 mm of origin made a hover that drifted 0.9 mm look three times too
        cautious. The heading's gauge is not subtracted: the filter carries it about the vehicle, entangled with
        the map, and subtracting the start's yaw variance leaves no positive covariance; :func:`accuracy` leaves the
        heading out of a turned run's NEES instead."""
        if self.gauge is None:
            return cov
        out = np.array(cov, dtype=float, copy=True)
        out[..., 0:3, 0:3] -= self.gauge
        # A start again (the camera lost) brings a gauge of its own: where less is left than the start held, the
        # filter's covariance is kept as it is (cautious) rather than a position covariance that is no covariance.
        lost = np.linalg.eigvalsh(out[..., 0:3, 0:3])[..., 0] <= 0.0
        out[lost] = np.asarray(cov, dtype=float)[lost]
        return out


def start_alignment(result: ReplayResult, truth, point_b: np.ndarray) -> StartAlignment | None:
    """For runs that never had an absolute position: the shift (and, when the heading was the frame's own,
    the turn) that puts the first valid estimated pose on the truth. A camera-only run (``local_position``)
    is always turned: even a heading it was given at the start is carried, in a start in motion, through
    the seconds before the visual-inertial start by a propagation it cannot correct."""
    status, traj = result.estimator.status(), result.trajectory
    if status.position_initialized or len(traj.t_ns) == 0:
        return None
    valid = np.flatnonzero(traj.valid)
    if len(valid) == 0:
        return None
    t0 = max(int(traj.t_ns[valid[0]]), int(truth.t_ns[0]))
    k = valid[min(int(np.searchsorted(traj.t_ns[valid], t0)), len(valid) - 1)]
    if traj.t_ns[k] < t0 or t0 > int(truth.t_ns[-1]):
        return None
    p_true, q_true = interpolate_poses(np.array([traj.t_ns[k]]), truth.t_ns, truth.p, truth.q)
    rotation = np.eye(3)
    turn = (not status.heading_aligned or status.local_position) and q_true is not None
    if turn:
        rotation = so3_exp(np.array([0.0, 0.0, float(yaw_of(q_true[0]) - yaw_of(traj.q[k]))]))
    # The start's origin variance: a run without an absolute position never learns it.
    gauge = result.covariances.cov[0][0:3, 0:3].copy() if len(result.covariances.t_ns) else None
    return StartAlignment(rotation, traj.p[k] + quat_to_rot(traj.q[k]) @ point_b, p_true[0], turn, gauge,
                          int(traj.t_ns[k]))


def visual_start_report(result: ReplayResult) -> dict | None:
    """Why the visual-inertial start waited, each change of the check that held it with what it measured
    (``VisualStartProgress``), and, if it never started, where it stood at the end; None without one."""
    status = result.estimator.status()
    if not status.visual_start_history and status.visual_start_waiting is None:
        return None
    def entry(p) -> dict:
        return {"t_s": round((p.t_ns - result.data_t0_ns) * 1e-9, 3), **p.as_dict()}
    out: dict[str, Any] = {"attempts": status.visual_start_attempts, "waited": [entry(p) for p in status.visual_start_history]}
    if status.visual_start_waiting is not None:
        out["still_waiting"] = entry(status.visual_start_waiting)
    return out


def _stats(values: list[float] | np.ndarray, digits: int = 3) -> dict:
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return {"mean": None, "max": None}
    return {"mean": round(float(v.mean()), digits), "median": round(float(np.median(v)), digits),
            "p95": round(float(np.percentile(v, 95)), digits), "max": round(float(v.max()), digits)}


def camera_summary(result: ReplayResult) -> dict | None:
    """Landmarks, matches and timing of the camera frames of a replay (None without frames)."""
    frames = result.frames
    if not frames:
        return None
    status = result.estimator.status()
    used = [f for f in frames if f.accepted]
    sources: dict[str, int] = {}
    for f in used:
        if f.depth_source:
            sources[f.depth_source] = sources.get(f.depth_source, 0) + len(f.new_ids)
    timing = {name: _stats([f.timing_ms[name] for f in used if f.timing_ms]) for name in ("predict", "associate", "update", "map", "total")}
    timing["extract"] = _stats(result.extract_ms)
    matches = status.counts.get("camera_match")
    return {
        "detector": result.detector,
        "frames": len(frames),
        "frames_used": len(used),
        "landmarks_in_map": _stats([f.n_landmarks for f in used], 1),
        "landmarks_in_view": _stats([f.candidates for f in used], 1),
        "matches_per_frame": _stats([f.n_matches for f in used], 1),
        "landmarks_initialised": status.landmarks_initialised,
        "landmarks_deleted": dict(status.landmarks_deleted),
        "depth_prior_sources": sources,
        "rejected_matches": dict(sorted(matches["rejected"].items())) if matches is not None else {},
        "timing_ms": timing,
        "time_offset_ms": status.camera_time_offset_ms(),
        "extrinsics": status.camera_mounting_document(),
    }


def mounting_lines(mounting: dict) -> list[str]:
    """The camera mounting's estimated correction, per body axis, for the summary."""
    rot, tr = mounting["rotation_deg"], mounting["translation_mm"]
    turn = ", ".join(f"{e:+.3f} ± {s:.3f}" for e, s in zip(rot["estimate"], rot["sigma"]))
    shift = ", ".join(f"{e:+.1f} ± {s:.1f}" for e, s in zip(tr["estimate"], tr["sigma"]))
    return [f"  camera mounting beyond the configured one (body x, y, z): rotation {turn} deg (R_BC = Exp(φ) R_BC as "
            f"configured), translation {shift} mm"]


# What each measurement count is, for a person reading the summary (the JSON keeps the short names).
COUNT_LABELS = {
    "imu": "IMU samples",
    "gps": "GPS fixes",
    "still": "still-period updates (zero velocity and gyro bias while at rest)",
    "level": "levelling updates (gravity as a tilt reference while the heading is unknown)",
    "camera_match": "camera matches",
    "camera": "camera frames",
}


def event_lines(report: dict, limit: int = 20) -> list[str]:
    """The estimator's events (start-up, alignment, resets), times from the first IMU sample."""
    events = sorted(report.get("events", []), key=lambda e: e["t_s"])
    lines = [f"  t={e['t_s']:8.3f} s  {e['message']}" for e in events[:limit]]
    if len(events) > limit:
        lines.append(f"  … {len(events) - limit} more in the report's events")
    return (["events (seconds from the first IMU sample):"] + lines) if lines else []


def smoothing_lines(report: dict) -> list[str]:
    """``replay --smooth``: the three kinds of pose side by side."""
    sm = report.get("smoothing")
    if sm is None:
        return []
    lines = ["  pose kind    position RMSE   / GPS   attitude RMSE   NEES mean"]
    for kind in ("filtered", "smoothed", "fixed_lag"):
        row = sm.get(kind)
        if row is None:
            continue
        def f(key: str, fmt: str) -> str:
            return "n/a" if row.get(key) is None else format(row[key], fmt)
        name = f"fixed lag {sm['lag_s']:g} s" if kind == "fixed_lag" else kind
        lines.append(f"  {name:<12} {f('position_rmse_m', '.4f'):>9} m   {f('position_rmse_over_gps', '.3f'):>6}   "
                     f"{f('attitude_rmse_deg', '.3f'):>9} deg   {f('nees_mean', '.2f'):>8}")
    lines.append(f"  smoothing: {sm['steps']} steps in {sm['segments']} segment(s), backward pass {sm['backward_s']:.2f} s "
                 f"({100 * (sm['backward_over_replay'] or 0):.0f} % of the replay), {sm['disk_mb']} MB on disk while it ran")
    return lines


def summary_lines(report: dict) -> list[str]:
    """The few numbers a person looks at first."""
    def fmt(key: str, unit: str = "", scale: float = 1.0, digits: int = 4) -> str:
        value = report.get(key)
        return "n/a" if value is None else f"{value * scale:.{digits}f}{unit}"

    head = f"dataset {report['dataset']}  variant {report['variant']}  sensors {','.join(report['sensor_set'])}"
    if "no_scores" in report:
        lines = [head, f"  no scores: {report['no_scores']}"]
    else:
        lines = [head] + score_lines(report, fmt)
    lines += visual_start_lines(report)
    return lines + count_lines(report)


def visual_start_lines(report: dict) -> list[str]:
    """Why the visual-inertial start waited (the last reason before it started), or still waits."""
    vs = report.get("visual_start")
    if not vs:
        return []
    if "still_waiting" in vs:
        w = vs["still_waiting"]
        return [f"  visual-inertial start: not started after {vs['attempts']} attempts; at {w['t_s']:.1f} s {w['text']}"]
    held = [w for w in vs["waited"] if w["check"] not in ("window", "confirming")]  # what held it, not the wait to agree
    if not held:
        return []
    w = held[-1]
    return [f"  visual-inertial start: after {vs['attempts']} attempts; the last hold, from {w['t_s']:.1f} s: {w['text']}"]


def score_lines(report: dict, fmt) -> list[str]:
    """Accuracy and consistency against the truth."""
    lines = [
        f"  position RMSE {fmt('position_rmse_m', ' m')}   GPS RMSE {fmt('gps_rmse_m', ' m')}   ratio {fmt('position_rmse_over_gps', '', 1, 3)}",
        f"  attitude RMSE {fmt('attitude_rmse_deg', ' deg', 1, 3)}"
        + (f" ({fmt('attitude_rmse_with_heading_deg', ' deg', 1, 3)} once the heading is placed)"
           if "attitude_rmse_with_heading_deg" in report else "")
        + f"   final drift {fmt('final_drift_m', ' m')}"
        + (f" ({fmt('drift_percent', ' %', 1, 2)} of {fmt('distance_travelled_m', ' m', 1, 1)} travelled)"
           if report.get("distance_travelled_m") else ""),
    ]
    if "nees" in report:
        n = report["nees"]
        lo, hi = n["band_per_sample"]
        verdict = "inside" if n["mean_in_band"] else "OUTSIDE"
        lines.append(f"  NEES mean {n['nees_mean']:.2f} ({n['dof']} dof; 95% band {lo:.2f}-{hi:.2f}: {verdict}; {100 * n['fraction_in_band']:.0f}% of samples in band)")
    if "position_reference" in report:
        turned = (" and its heading turned onto the truth's; the NEES leaves the heading out"
                  if report["position_reference"].get("heading_aligned") else "")
        lines.append(f"  (no absolute position: scored with the start put on the truth{turned})")
    return lines


def count_lines(report: dict) -> list[str]:
    """Camera, smoothing, speed, counts, faults and resets."""
    lines: list[str] = []
    cam = report.get("camera")
    if cam is not None:
        t = cam["timing_ms"]
        lines.append(
            f"  camera ({cam['detector']}): {cam['frames_used']}/{cam['frames']} frames, {cam['matches_per_frame']['mean']} matches "
            f"per frame, map {cam['landmarks_in_map']['mean']} landmarks (max {cam['landmarks_in_map']['max']}), "
            f"{cam['landmarks_initialised']} initialised; extract {t['extract']['mean']} ms, filter {t['total']['mean']} ms per frame"
        )
        offset = cam.get("time_offset_ms")
        if offset is not None:
            lines.append(f"  camera time offset beyond the configured one: {offset['estimate']:+.2f} ± {offset['sigma']:.2f} ms "
                         "(a frame was taken this much after its stamp)")
        mounting = cam.get("extrinsics")
        if mounting is not None:
            lines += mounting_lines(mounting)
    lines += smoothing_lines(report)
    lines.append(f"  {report['duration_s']:.1f} s of data in {report['wall_s']:.2f} s: {report['realtime_factor']}x real time"
                 + (f" ({report['kernels']})" if report.get("kernels") else ""))
    for name, c in report["sensors"].items():
        if not c["received"]:
            continue  # e.g. no levelling updates when the heading was known from the start
        rej = ", ".join(f"{k} {v}" for k, v in c["rejected"].items()) or "none"
        flagged = ", ".join(f"{k} {v}" for k, v in c.get("flagged", {}).items())
        label = COUNT_LABELS.get(name, name)
        lines.append(f"  {label}: {c['used']} used of {c['received']}; rejected: {rej}" + (f"; flagged: {flagged}" if flagged else ""))
    for fault in report.get("faults", []):
        lines.append(f"  fault {fault['spec']}: {fault['samples_affected']} samples dropped or changed")
    for rel, steps in (report.get("clock_steps") or {}).items():
        lines += [f"  {rel}: {step}" for step in steps]
    noise = report.get("gps_noise") or {}
    if noise.get("fixes_adjusted"):
        lines.append(f"  GPS accuracy claims not believed: {noise['fixes_adjusted']} fixes weighed with the noise measured"
                     + (f" ({noise['text']})" if noise.get("text") else ""))
    health = report.get("health") or {}
    if health.get("resets"):
        lines.append(f"  filter resets: {', '.join(f'{k} {v}' for k, v in health['resets'].items())} (see the events)")
    return lines
