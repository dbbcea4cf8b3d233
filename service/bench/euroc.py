"""Every EuRoC flight on disk, end to end: imported, replayed with both models, scored — one table.

A measurement repeatable on flights this program was never tuned on: each
flight is imported the same way (the IMU as recorded; a GPS made from the truth at 10 Hz with
σ_xy 2 cm, σ_z² = 2 σ_xy², seed 1; the heading unknown; the one vehicle file
``config/euroc_vi_sensor.yaml``), replayed through the runtime with IMU and GPS, and scored
from 15 s after the truth starts:

- position RMSE of the tracked point after a rigid alignment (rotation and translation) of the
  estimate onto the truth, against the raw GPS's RMSE over the same span;
- attitude: RMS of the error that varies with time — the constant world rotation between truth
  and estimate (``metrics.mean_world_rotation``: the motion-capture frame's "up" is a fraction
  of a degree off the vertical the estimate levels itself to) taken off — over the poses that
  carry a heading (before the heading is placed the outputs say it is unknown: quality 0);
- NEES over position and attitude (6 dof; 3 without orientation truth) of every pose from 15 s,
  the heading's published sigma included, with the same world rotation taken off;
- time to the first pose with a position (from switch-on), time from the truth's motion onset
  to the heading's placement, resets, and the replay's real-time factor;
- the same position, attitude and NEES figures for the smoothed poses (``replay --smooth``: the
  backward pass over the whole flight) and the fixed-lag ones (``smoothing.fixed_lag_s``, what
  the daemon's history answers once the lag has passed), and what the backward pass cost
  against the plain replay's wall time.

Flights are found under ``$VTOLPOSE_EUROC_DATA``, else ``../shared/data`` next to the working
directory or to the repository: any folder with ``mav0/imu0/data.csv``; a ``truth.tum`` beside
``mav0`` is used as its truth (see ``vtolpose import euroc --truth``).
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

import vtolpose
from vtolpose.service.bench.rows import Row as BenchRow
from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.files.euroc_import import TRUTH_FOLDERS, import_euroc
from vtolpose.estimator import (
    chi2_band, EventKind, gps_error_rmse, interpolate_poses, mean_world_rotation, motion_onset, nees,
    pose_errors_for_nees, quat_to_rot, rigid_alignment, rot_to_quat, rotation_angle,
)
from vtolpose.service.replay.session import CovarianceSamples, ReplayResult, Trajectory, replay
from vtolpose.service.replay.smoothing import replay_smoothed
from vtolpose.service.runtime.kernels import load_compiled_kernels

Row = tuple[str, float, str, str] | BenchRow
DATA_ENV = "VTOLPOSE_EUROC_DATA"
SCORE_FROM_S = 15.0
GPS_RATE_HZ, GPS_SIGMA_M, GPS_SEED = 10.0, 0.02, 1
VARIANTS = ("biases", "thesis")


@dataclass(frozen=True)
class Flight:
    name: str
    source: Path
    truth_file: Path | None


@dataclass(frozen=True)
class PoseScore:
    """One kind of pose of one replay (filtered, smoothed or fixed-lag), scored as the module docstring says."""

    position_rmse_m: float
    attitude_rms_deg: float | None
    nees_mean: float
    nees_dof: int
    nees_in_band: float
    alignment_deg: float
    world_rotation_deg: float
    speed_bands: tuple[float | None, ...] = ()  # position RMSE per band of SPEED_BANDS_M_S (None: too few samples)
    worst_window: tuple[float, float] | None = None  # the worst WINDOW_S window's position RMSE and its start [s]


POSITION_TARGET = "<= 0.55"  # the default model's position over the GPS's error, on every real flight
SPEED_BANDS_M_S = (0.5, 1.0, 1.5)  # the bands' edges: < 0.5, 0.5-1, 1-1.5, > 1.5 m/s
WINDOW_S = 10.0  # the window of the worst stretch
MIN_BAND_SAMPLES = 20  # fewer samples in a band: no figure


def speed_band_rmse(t_ns: np.ndarray, p_true: np.ndarray, error: np.ndarray) -> tuple[float | None, ...]:
    """Position RMSE where the truth's speed lies in each band of :data:`SPEED_BANDS_M_S`: whether the error
    runs away with speed."""
    speed = np.linalg.norm(np.gradient(p_true, t_ns * 1e-9, axis=0), axis=1) if len(t_ns) > 1 else np.zeros(len(t_ns))
    band = np.searchsorted(np.asarray(SPEED_BANDS_M_S), speed, side="right")
    squared = np.sum(error**2, axis=1)
    out = []
    for k in range(len(SPEED_BANDS_M_S) + 1):
        inside = band == k
        out.append(float(np.sqrt(np.mean(squared[inside]))) if np.count_nonzero(inside) >= MIN_BAND_SAMPLES else None)
    return tuple(out)


def worst_window(t_ns: np.ndarray, error: np.ndarray, t0_ns: int, window_s: float = WINDOW_S,
                 step_s: float = 1.0) -> tuple[float, float] | None:
    """The ``window_s`` stretch (starts ``step_s`` apart) with the largest position RMSE: (RMSE, its start after
    ``t0_ns`` in seconds); None when the scored span is shorter than one window."""
    if len(t_ns) < 2 or (t_ns[-1] - t_ns[0]) * 1e-9 < window_s:
        return None
    cumulative = np.concatenate([[0.0], np.cumsum(np.sum(error**2, axis=1))])
    starts = np.arange(int(t_ns[0]), int(t_ns[-1] - window_s * 1e9) + 1, int(step_s * 1e9))
    lo = np.searchsorted(t_ns, starts)
    hi = np.searchsorted(t_ns, starts + int(window_s * 1e9))
    count = np.maximum(hi - lo, 1)
    rmse = np.sqrt((cumulative[hi] - cumulative[lo]) / count)
    k = int(np.argmax(rmse))
    return float(rmse[k]), (int(starts[k]) - t0_ns) * 1e-9


@dataclass(frozen=True)
class FlightScore:
    flight: str
    variant: str
    position_rmse_m: float
    gps_rmse_m: float
    attitude_rms_deg: float | None  # poses with a heading, from SCORE_FROM_S; None without orientation truth
    nees_mean: float
    nees_dof: int
    nees_in_band: float  # fraction of samples inside the per-sample 95 % band
    first_pose_s: float | None  # switch-on to the first pose with a position
    heading_s: float | None  # motion onset to the heading's placement (None: never placed)
    onset_s: float | None  # motion onset after the truth starts
    resets: int
    realtime_factor: float
    alignment_deg: float  # rotation of the rigid alignment (a check: the GPS frame is the truth's)
    world_rotation_deg: float  # constant world rotation taken off the attitude (0 without orientation truth)
    smoothed: PoseScore | None = None
    fixed_lag: PoseScore | None = None
    backward_over_replay: float | None = None  # the backward pass's wall time over the plain replay's
    speed_bands: tuple[float | None, ...] = ()  # the filtered position's RMSE per speed band (see PoseScore)
    worst_window: tuple[float, float] | None = None

    @property
    def ratio(self) -> float:
        return self.position_rmse_m / self.gps_rmse_m


def data_roots() -> list[Path]:
    """Where EuRoC flights may be: ``$VTOLPOSE_EUROC_DATA``, else ``../shared/data`` from here or the repository."""
    if os.environ.get(DATA_ENV):
        return [Path(os.environ[DATA_ENV])]
    repo = Path(vtolpose.__file__).resolve().parent
    return list(dict.fromkeys(p.resolve() for p in (Path.cwd().parent / "shared" / "data", repo.parent / "shared" / "data")))


def find_flights(roots: list[Path]) -> list[Flight]:
    """Every folder under ``roots`` (three levels deep at most) that holds a EuRoC IMU and a truth to score
    against (``truth.tum`` beside ``mav0``, or one of EuRoC's truth folders), by name. A recording without
    one (a hand-held recording of a user's own) is no bench flight."""
    found: dict[str, Flight] = {}
    for root in roots:
        if not root.is_dir():
            continue
        for imu in sorted(root.glob("**/mav0/imu0/data.csv")):
            folder = imu.parents[2]
            if len(folder.relative_to(root).parts) > 3:
                continue
            truth = folder / "truth.tum"
            if not (truth.is_file() or any((folder / "mav0" / t / "data.csv").is_file() for t in TRUTH_FOLDERS)):
                continue
            name = folder.name.removeprefix("euroc_").upper()
            found.setdefault(name, Flight(name, folder, truth if truth.is_file() else None))
    return sorted(found.values(), key=lambda f: f.name)


def aligned_position_errors(traj: Trajectory, dataset: Dataset
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The tracked point's error at the truth's samples from SCORE_FROM_S, after the rigid alignment: (the truth
    samples scored as a mask, the estimate's rotations there, the alignment's rotation and translation, errors)."""
    truth, point_b = dataset.truth(), dataset.calibration.truth_point_b
    t_from = int(truth.t_ns[0] + SCORE_FROM_S * 1e9)
    inside = (truth.t_ns >= max(t_from, int(traj.t_ns[0]))) & (truth.t_ns <= traj.t_ns[-1])
    p_est, q_est = interpolate_poses(truth.t_ns[inside], traj.t_ns, traj.p, traj.q)
    R_est = quat_to_rot(q_est)
    R_al, t_al = rigid_alignment(p_est + R_est @ point_b, truth.p[inside])
    return inside, R_est, R_al, t_al, (p_est + R_est @ point_b) @ R_al.T + t_al - truth.p[inside]


def score_poses(traj: Trajectory, cov: CovarianceSamples, dataset: Dataset, placed: int | None,
                known_from_start: bool) -> PoseScore:
    """Position after a rigid alignment, attitude with the constant world rotation off (poses with a
    heading: from ``placed``, or all if ``known_from_start``), NEES, from SCORE_FROM_S."""
    truth, point_b = dataset.truth(), dataset.calibration.truth_point_b
    t_from = int(truth.t_ns[0] + SCORE_FROM_S * 1e9)
    inside, R_est, R_al, t_al, error = aligned_position_errors(traj, dataset)
    t = truth.t_ns[inside]
    attitude, world = None, np.eye(3)
    if truth.q is not None:
        with_heading = t >= placed if placed is not None else np.zeros(len(t), dtype=bool)
        if known_from_start:  # a heading known from the start
            with_heading[:] = True
        if np.any(with_heading):
            q_aligned = rot_to_quat(R_al @ R_est[with_heading])
            world = mean_world_rotation(q_aligned, truth.q[inside][with_heading])
            q_aligned = rot_to_quat(world @ quat_to_rot(q_aligned))
            attitude = float(np.degrees(np.sqrt(np.mean(rotation_angle(truth.q[inside][with_heading], q_aligned) ** 2))))
    c = cov.t_ns >= t_from
    turn = np.zeros((6, 6))
    turn[0:3, 0:3], turn[3:6, 3:6] = R_al, world @ R_al
    q_cov = rot_to_quat(world @ R_al @ quat_to_rot(cov.q[c]))
    p_cov = cov.p[c] @ R_al.T + t_al
    err, c_err, dof = pose_errors_for_nees(cov.t_ns[c], p_cov, q_cov, turn @ cov.cov[c] @ turn.T, truth, point_b)
    values = nees(err, c_err)
    lo, hi = chi2_band(dof)
    return PoseScore(float(np.sqrt(np.mean(np.sum(error**2, axis=1)))), attitude, float(np.mean(values)), dof,
                     float(np.mean((values >= lo) & (values <= hi))), _angle_deg(R_al), _angle_deg(world),
                     speed_band_rmse(t, truth.p[inside], error), worst_window(t, error, int(truth.t_ns[0])))


def scored_gps_rmse(dataset: Dataset) -> float:
    """The GPS fixes' own error over the scored stretch (from SCORE_FROM_S): every ratio's denominator."""
    truth, gps = dataset.truth(), dataset.gps()
    keep = gps.t_ns >= int(truth.t_ns[0] + SCORE_FROM_S * 1e9)
    return float(gps_error_rmse(type(gps)(gps.t_ns[keep], gps.p_ned[keep], gps.sigma_h[keep], gps.sigma_v[keep]), truth,
                                dataset.calibration.gps.lever_arm_b, dataset.calibration.truth_point_b)["rmse_m"])


def scored_position_rmse(traj: Trajectory, dataset: Dataset) -> float:
    """Position RMSE of any trajectory (t_ns, p, q of the body) as the table scores vtolpose's: the tracked point at
    the truth's samples from SCORE_FROM_S, after the rigid alignment (:func:`aligned_position_errors`)."""
    error = aligned_position_errors(traj, dataset)[4]
    return float(np.sqrt(np.mean(np.sum(error**2, axis=1))))


def at_fix_position_rmse(traj: Trajectory, dataset: Dataset) -> float:
    """Position RMSE as a smoother scores itself: the first pose at or after each fix (that fix's update) against the
    truth at its time, no alignment, from SCORE_FROM_S; between fixes nothing is scored."""
    truth, gps, point_b = dataset.truth(), dataset.gps(), dataset.calibration.truth_point_b
    lo, hi = max(int(truth.t_ns[0] + SCORE_FROM_S * 1e9), int(traj.t_ns[0])), min(int(truth.t_ns[-1]), int(traj.t_ns[-1]))
    k = np.searchsorted(traj.t_ns, gps.t_ns[(gps.t_ns >= lo) & (gps.t_ns <= hi)])
    t = traj.t_ns[k]
    p = traj.p[k] + quat_to_rot(traj.q[k]) @ point_b
    p_truth, _ = interpolate_poses(t, truth.t_ns, truth.p)
    return float(np.sqrt(np.mean(np.sum((p - p_truth) ** 2, axis=1))))


def score(result: ReplayResult, dataset: Dataset, flight: str, variant: str,
          plain_wall_s: float | None = None) -> FlightScore:
    """The table's figures for one replay (see the module docstring); with ``result.smoothing`` (a
    ``replay_smoothed`` run) the smoothed and fixed-lag ones too."""
    status, traj, truth = result.estimator.status(), result.trajectory, dataset.truth()
    placed = status.heading_placement.t_ns if status.heading_placement is not None else None
    known = status.heading_aligned and placed is None
    filtered = score_poses(traj, result.covariances, dataset, placed, known)
    gps_rmse = scored_gps_rmse(dataset)
    imu_t0 = int(dataset.imu_raw().t_ns[0])
    positioned = status.first(EventKind.POSITION_INITIALISED)
    onset = motion_onset(truth)
    sm = result.smoothing
    smoothed = fixed_lag = backward = None
    if sm is not None:
        smoothed = score_poses(sm.smoothed, sm.smoothed_cov, dataset, placed, known)
        if len(sm.fixed_lag.t_ns) >= 2:
            fixed_lag = score_poses(sm.fixed_lag, sm.fixed_lag_cov, dataset, placed, known)
        backward = sm.backward_s / (plain_wall_s or result.wall_s)
    return FlightScore(
        flight, variant, filtered.position_rmse_m, float(gps_rmse), filtered.attitude_rms_deg,
        filtered.nees_mean, filtered.nees_dof, filtered.nees_in_band,
        None if positioned is None else (positioned.t_ns - imu_t0) * 1e-9,
        None if placed is None or onset is None else (placed - onset) * 1e-9,
        None if onset is None else (onset - int(truth.t_ns[0])) * 1e-9,
        status.reset_counter, (plain_wall_s and result.duration_s / plain_wall_s) or
        (result.duration_s / result.wall_s if result.wall_s > 0 else float("nan")),
        filtered.alignment_deg, filtered.world_rotation_deg, smoothed, fixed_lag, backward,
        filtered.speed_bands, filtered.worst_window,
    )


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def imported_flight(flight: Flight, work: Path, seed: int = GPS_SEED) -> Dataset:
    """``flight`` imported into ``work`` the one way every flight is (GPS from the truth at 10 Hz, 2 cm, seed 1;
    another ``seed`` draws the GPS's noise again over the same truth)."""
    out = work / flight.name
    import_euroc(flight.source, out, gps_rate_hz=GPS_RATE_HZ, gps_sigma_m=GPS_SIGMA_M, seed=seed,
                 overwrite=True, truth_file=flight.truth_file, camera=False)
    return Dataset.open(out)


def run_flight(flight: Flight, work: Path, variants: tuple[str, ...] = VARIANTS, smooth: bool = False) -> list[FlightScore]:
    """Import ``flight`` into ``work`` (:func:`imported_flight`), replay it with IMU and GPS per variant (and
    with ``--smooth``), score it."""
    dataset = imported_flight(flight, work)
    scores = []
    for variant in variants:
        cfg = load_config(None, {"estimator": {"variant": variant}})
        plain = replay(dataset, cfg, ["imu", "gps"])  # the real-time factor and the backward pass's yardstick
        result = replay_smoothed(dataset, cfg, sensors=["imu", "gps"]) if smooth else plain
        scores.append(score(result, dataset, flight.name, variant, plain.wall_s))
    return scores


def _fmt(value: float | None, spec: str, unit: str = "") -> str:
    return "—" if value is None or not np.isfinite(value) else f"{value:{spec}}{unit}"


def table_lines(scores: list[FlightScore]) -> list[str]:
    """The results table (Markdown), one row per flight and model."""
    lines = [
        "| flight | model | position RMSE | GPS RMSE | ratio | attitude RMS | NEES (in band) | first pose | heading | resets | × real time |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in scores:
        heading = "never" if s.heading_s is None else f"{s.heading_s:.1f} s after onset"
        lines.append(
            f"| {s.flight} | {s.variant} | {s.position_rmse_m:.4f} m | {s.gps_rmse_m:.4f} m | {s.ratio:.3f} | "
            f"{_fmt(s.attitude_rms_deg, '.2f', '°')} | {s.nees_mean:.2f} ({s.nees_dof} dof, {100 * s.nees_in_band:.0f} %) | "
            f"{_fmt(s.first_pose_s, '.1f', ' s')} | {heading} | {s.resets} | {s.realtime_factor:.0f} |"
        )
    return lines


def speed_lines(scores: list[FlightScore]) -> list[str]:
    """Where the filtered position's error lies (Markdown): its RMSE per band of the truth's speed, and the worst
    10-s stretch with its start after the truth's first sample."""
    edges = SPEED_BANDS_M_S
    names = [f"< {edges[0]:g}"] + [f"{a:g}-{b:g}" for a, b in zip(edges, edges[1:])] + [f"> {edges[-1]:g} m/s"]
    lines = ["| flight | model | " + " | ".join(names) + f" | worst {WINDOW_S:g} s |", "|---" * (len(names) + 3) + "|"]
    for s in scores:
        bands = " | ".join(_fmt(b, ".4f", " m") for b in s.speed_bands) if s.speed_bands else " | ".join("—" for _ in names)
        worst = "—" if s.worst_window is None else f"{s.worst_window[0]:.4f} m from {s.worst_window[1]:.0f} s"
        lines.append(f"| {s.flight} | {s.variant} | {bands} | {worst} |")
    return lines


def smoothing_lines(scores: list[FlightScore]) -> list[str]:
    """The smoothed and fixed-lag columns (Markdown): position RMSE (ratio to the GPS), attitude RMS, NEES."""
    lines = [
        "| flight | model | filtered | smoothed | fixed lag | attitude: filtered / smoothed / fixed lag | "
        "NEES: smoothed / fixed lag (in band) | backward pass |",
        "|---|---|---|---|---|---|---|---|",
    ]

    def pos(k: PoseScore | None, gps: float) -> str:
        return "—" if k is None else f"{k.position_rmse_m:.4f} m ({k.position_rmse_m / gps:.3f})"

    def nees_text(k: PoseScore | None) -> str:
        return "—" if k is None else f"{k.nees_mean:.2f} ({100 * k.nees_in_band:.0f} %)"

    for s in scores:
        sm, fl = s.smoothed, s.fixed_lag
        attitude = " / ".join(_fmt(a, ".2f", "°") for a in (s.attitude_rms_deg, sm and sm.attitude_rms_deg,
                                                             fl and fl.attitude_rms_deg))
        lines.append(
            f"| {s.flight} | {s.variant} | {s.position_rmse_m:.4f} m ({s.ratio:.3f}) | {pos(sm, s.gps_rmse_m)} | "
            f"{pos(fl, s.gps_rmse_m)} | {attitude} | {nees_text(sm)} / {nees_text(fl)} | "
            f"{_fmt(s.backward_over_replay, '.2f', ' × replay')} |"
        )
    return lines


def flights_or_skip(bench: str, echo: Callable[[str], None]) -> list:
    """The EuRoC flights under the data roots; none: a skip line that says where to put them."""
    roots = data_roots()
    flights = find_flights(roots)
    if not flights:
        echo(f"  {bench}: skipped, no EuRoC flight (mav0/imu0/data.csv) under {', '.join(map(str, roots))}; "
             f"set {DATA_ENV} to the folder that holds them")
    return flights


def bench_euroc(echo: Callable[[str], None] = print) -> list[Row]:
    """Every EuRoC flight under ../shared/data: import, replay both models, score (the table of docs/results.md)."""
    flights = flights_or_skip("euroc", echo)
    if not flights:
        return []
    load_compiled_kernels(backward_pass=True)  # once per process, before the first replay (not in its time)
    scores: list[FlightScore] = []
    with tempfile.TemporaryDirectory() as tmp:
        for flight in flights:
            scores.extend(run_flight(flight, Path(tmp), smooth=True))
    for line in table_lines(scores) + [""] + speed_lines(scores) + [""] + smoothing_lines(scores):
        echo("  " + line)
    rows: list[Row] = [BenchRow(f"{s.flight} {s.variant}: position / GPS", s.ratio, "ratio",
                                f"attitude {_fmt(s.attitude_rms_deg, '.2f', ' deg')}, NEES {s.nees_mean:.2f}, {s.resets} resets",
                                POSITION_TARGET if s.variant == "biases" else None)
                       for s in scores]
    rows += [BenchRow(f"{s.flight} {s.variant}: worst {WINDOW_S:g} s / GPS", s.worst_window[0] / s.gps_rmse_m, "ratio",
                      f"from {s.worst_window[1]:.0f} s") for s in scores if s.worst_window is not None]
    for s in scores:  # the smoothing's targets (docs/smoothing.md), default variant
        if s.variant != "biases" or s.smoothed is None:
            continue
        rows.append(BenchRow(f"{s.flight} smoothed: position / GPS", s.smoothed.position_rmse_m / s.gps_rmse_m, "ratio",
                             f"attitude {_fmt(s.smoothed.attitude_rms_deg, '.2f', ' deg')}", "<= 0.3"))
        if s.smoothed.attitude_rms_deg is not None:
            rows.append(BenchRow(f"{s.flight} smoothed: attitude RMS", s.smoothed.attitude_rms_deg, "deg", "", "<= 1.0"))
        if s.fixed_lag is not None:
            rows.append(BenchRow(f"{s.flight} fixed lag: position / GPS", s.fixed_lag.position_rmse_m / s.gps_rmse_m,
                                 "ratio", "", "<= 0.45"))
        rows.append(BenchRow(f"{s.flight} backward pass / replay", s.backward_over_replay, "x", "", "<= 0.5"))
    return rows
