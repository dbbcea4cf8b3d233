"""Where the EuRoC position error comes from: scoring, start-up, GPS timing, IMU noise (``bench --only euroc-causes``).

The GTSAM reference reports its error at the GPS fixes only (the newest state right after each fix); the
``euroc`` table scores every truth sample, between the fixes too, where the causal estimate has been
predicted for up to 100 ms. This bench scores the default model's plain replay (IMU and GPS, imported as
``service.bench.euroc`` does) three ways and then moves one input at a time:

- the ratio to the GPS's error at every truth sample (the ``euroc`` table's), and at the fix times (the
  reference's way), and the RMSE by time since the last fix: what the prediction between fixes adds;
- the ratio per stretch of the flight against the GPS's error in the same stretch: what the start-up
  (heading placed in motion, biases settling) costs against the steady state;
- the same replay with the GPS's noise drawn again (``OTHER_GPS_SEEDS``; the import's seed 1 draws the same
  noise sequence for every flight): what of each figure, and of each stretch's, is that one draw's;
- the same ratio with the GPS stamps moved by ``±TIMING_SHIFTS_S`` (``calibration.gps.time_offset_s``):
  whether the fixes and the IMU share one clock;
- the same ratio with the vehicle file's white noise scaled by ``NOISE_SCALES``: whether the inflated
  constant is what holds the position back;
- what a linear filter can reach at all with the vehicle file's white density (:func:`steady_state_ratio`:
  each axis a double integrator driven by that noise, the fixes of the import), at the fixes and between;
- the IMU's own vibration floor in flight (``estimator.inertial.vibration``, 10-60 Hz, from SCORE_FROM_S)
  per axis, against the vehicle file's white densities: whether that constant is the vibration's level;
- below 3 Hz, where the IMU's own spectrum is the vehicle's motion, the accelerometer against the truth
  (``specific_force_residual``, flights with an attitude truth): what the white constant has to cover there.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.estimator import (DEFAULT_BAND_HZ, LOW_BANDS_HZ, band_densities, gps_error_rmse, interpolate_poses,
                                 quat_to_rot, specific_force_residual, vibration_floor)
from vtolpose.service.bench.euroc import GPS_RATE_HZ, GPS_SEED, SCORE_FROM_S, aligned_position_errors, flights_or_skip, imported_flight
from vtolpose.service.bench.rows import Row
from vtolpose.service.replay.session import replay
from vtolpose.service.runtime.kernels import load_compiled_kernels

GAP_EDGES_S = (0.02, 0.04, 0.06, 0.08)  # bands of time since the last fix: < 20 ms, 20-40, ..., > 80 ms
STRETCHES_S = (15.0, 30.0, 60.0, 90.0)  # stretches of the flight from the truth's start: 15-30, 30-60, 60-90, 90-end
TIMING_SHIFTS_S = (-0.01, 0.01)
NOISE_SCALES = {"accel_noise_density": (0.4, 1.6), "gyro_noise_density": (0.25,)}
MIN_SAMPLES = 20  # fewer samples in a band: no figure
FLOOR_DENSITIES = (0.04, 0.03, 0.02)  # m/s²/√Hz: the linear filter's floor at these besides the vehicle file's
OTHER_GPS_SEEDS = (2, 3, 4, 5)  # the GPS's noise drawn again: the spread of the ratio over draws of the same flight


def rmse_by_gap(t_ns: np.ndarray, error: np.ndarray, fix_t_ns: np.ndarray,
                edges_s: tuple[float, ...] = GAP_EDGES_S) -> tuple[float | None, ...]:
    """Position RMSE by time since the newest fix at or before each sample (samples before the first fix left
    out): how much the prediction between fixes adds."""
    k = np.searchsorted(fix_t_ns, t_ns, side="right") - 1
    heard = k >= 0
    since = (t_ns[heard] - fix_t_ns[k[heard]]) * 1e-9
    band = np.searchsorted(np.asarray(edges_s), since, side="right")
    squared = np.sum(error[heard] ** 2, axis=1)
    return tuple(float(np.sqrt(np.mean(squared[band == b]))) if np.count_nonzero(band == b) >= MIN_SAMPLES else None
                 for b in range(len(edges_s) + 1))


def stretch_ratios(t_rel_s: np.ndarray, error: np.ndarray, gps_t_rel_s: np.ndarray, gps_error: np.ndarray,
                   starts_s: tuple[float, ...] = STRETCHES_S) -> tuple[float | None, ...]:
    """The position's RMSE over the GPS's in each stretch from ``starts_s[i]`` to the next (the last to the end)."""
    out = []
    for a, b in zip(starts_s, (*starts_s[1:], np.inf)):
        mine = (t_rel_s >= a) & (t_rel_s < b)
        fixes = (gps_t_rel_s >= a) & (gps_t_rel_s < b)
        if np.count_nonzero(mine) < MIN_SAMPLES or np.count_nonzero(fixes) < MIN_SAMPLES:
            out.append(None)
            continue
        out.append(float(np.sqrt(np.mean(np.sum(error[mine] ** 2, axis=1)) / np.mean(np.sum(gps_error[fixes] ** 2, axis=1)))))
    return tuple(out)


def over_draws(draws: list[tuple[float, tuple[float | None, ...]]]) -> tuple[float, float, float, tuple[float | None, ...]]:
    """Replays of one flight under several draws of the GPS's noise, each (its ratio, its ratios per stretch):
    the ratios' mean, least and largest, and each stretch's mean over the draws that reach it (None: none does)."""
    ratios = [r for r, _ in draws]
    stretches = []
    for k in range(max(len(s) for _, s in draws)):
        known = [s[k] for _, s in draws if k < len(s) and s[k] is not None]
        stretches.append(float(np.mean(known)) if known else None)
    return float(np.mean(ratios)), min(ratios), max(ratios), tuple(stretches)


def steady_state_ratio(accel_density: float, rate_hz: float, sigma_h: float, sigma_v: float,
                       iterations: int = 3000) -> tuple[float, float]:
    """The position error over the GPS's of the steady-state Kalman filter for a double integrator per axis
    driven by white acceleration of ``accel_density`` [m/s²/√Hz], fixed at ``rate_hz`` with σ ``sigma_h``
    (x, y) and ``sigma_v`` (z): (right after a fix, averaged over the interval between fixes). No causal
    filter with that noise model does better; the between-fix figure is what every-sample scoring sees."""
    period, q = 1.0 / rate_hz, accel_density**2
    transition = np.array([[1.0, period], [0.0, 1.0]])
    noise = q * np.array([[period**3 / 3, period**2 / 2], [period**2 / 2, period]])
    after = between = 0.0
    for sigma in (sigma_h, sigma_h, sigma_v):
        P = np.eye(2)
        for _ in range(iterations):
            P = transition @ P @ transition.T + noise
            P = P - np.outer(P[:, 0], P[0]) / (P[0, 0] + sigma**2)
        s = np.linspace(0.0, period, 201)[:-1]
        after += P[0, 0]
        between += float(np.mean(P[0, 0] + 2 * s * P[0, 1] + s**2 * P[1, 1] + q * s**3 / 3))
    gps = 2 * sigma_h**2 + sigma_v**2
    return float(np.sqrt(after / gps)), float(np.sqrt(between / gps))


def _gps_errors(dataset: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """The fixes from SCORE_FROM_S inside the truth: their times and their errors against the truth's point."""
    truth, gps = dataset.truth(), dataset.gps()
    keep = (gps.t_ns >= truth.t_ns[0] + SCORE_FROM_S * 1e9) & (gps.t_ns <= truth.t_ns[-1])
    p_true, q_true = interpolate_poses(gps.t_ns[keep], truth.t_ns, truth.p, truth.q)
    if q_true is not None:
        lever, point = dataset.calibration.gps.lever_arm_b, dataset.calibration.truth_point_b
        p_true = p_true + quat_to_rot(q_true) @ (lever - point)
    return gps.t_ns[keep], gps.p_ned[keep] - p_true


def _ratio(dataset: Dataset, overrides: dict) -> tuple[float, object, np.ndarray]:
    """The default model's plain replay with ``overrides``: its position / GPS ratio (the ``euroc`` table's)."""
    result = replay(dataset, load_config(None, overrides), ["imu", "gps"])
    inside, _, _, _, error = aligned_position_errors(result.trajectory, dataset)
    gps = dataset.gps()
    truth = dataset.truth()
    keep = gps.t_ns >= truth.t_ns[0] + SCORE_FROM_S * 1e9
    gps_rmse = gps_error_rmse(type(gps)(gps.t_ns[keep], gps.p_ned[keep], gps.sigma_h[keep], gps.sigma_v[keep]), truth,
                              dataset.calibration.gps.lever_arm_b, dataset.calibration.truth_point_b)["rmse_m"]
    return float(np.sqrt(np.mean(np.sum(error**2, axis=1))) / gps_rmse), result, error


def _ratio_and_stretches(dataset: Dataset) -> tuple[float, tuple[float | None, ...], object, np.ndarray]:
    """The default model's plain replay: its ratio (the ``euroc`` table's), its ratios per stretch, the replay, errors."""
    ratio, result, error = _ratio(dataset, {})
    truth = dataset.truth()
    t = truth.t_ns[aligned_position_errors(result.trajectory, dataset)[0]]
    fix_t, fix_error = _gps_errors(dataset)
    by_stretch = stretch_ratios((t - truth.t_ns[0]) * 1e-9, error, (fix_t - truth.t_ns[0]) * 1e-9, fix_error)
    return ratio, by_stretch, result, error


def _fmt(value: float | None, spec: str) -> str:
    return "—" if value is None else f"{value:{spec}}"


def _low_band_line(name: str, dataset: Dataset, rows: list[Row]) -> str:
    """The accelerometer's error below 3 Hz against the truth, from SCORE_FROM_S (the readings come in body axes)."""
    truth, imu = dataset.truth(), dataset.imu()
    scored = truth.t_ns >= truth.t_ns[0] + int(SCORE_FROM_S * 1e9)
    gravity = np.array([0.0, 0.0, dataset.calibration.imu.gravity])  # NED: down
    residual, rate = specific_force_residual(imu.t_ns, imu.accel, truth.t_ns[scored], truth.p[scored], truth.q[scored],
                                             np.eye(3), gravity)
    edge = int(2 * rate)  # the low-pass's start and end
    densities = band_densities(residual[edge:-edge], rate)
    white = float(np.max(dataset.calibration.imu.noise.accel_noise_density))
    for (lo, hi), per_axis in zip(LOW_BANDS_HZ, densities):
        rows.append(Row(f"{name}: accelerometer error against the truth, {lo:g}-{hi:g} Hz (RMS of axes)",
                        float(np.sqrt(np.mean(per_axis**2))), "m/s²/√Hz", f"vehicle file {white:g}"))
    return (f"| {name} | " + " | ".join(" / ".join(f"{d:.3f}" for d in per_axis) for per_axis in densities)
            + f" m/s²/√Hz | {' / '.join(f'{b:.3f}' for b in residual.mean(axis=0))} m/s² | {white:g} |")


def bench_euroc_causes(echo: Callable[[str], None] = print) -> list[Row]:
    """Each EuRoC flight: the default model's ratio scored three ways, then with the GPS timing and the IMU's
    white noise moved one at a time, and under other draws of the GPS's noise (see the module docstring)."""
    flights = flights_or_skip("euroc-causes", echo)
    if not flights:
        return []
    load_compiled_kernels()
    gaps = [f"< {GAP_EDGES_S[0] * 1e3:g} ms"] + [f"{a * 1e3:g}-{b * 1e3:g}" for a, b in zip(GAP_EDGES_S, GAP_EDGES_S[1:])]
    gaps.append(f"> {GAP_EDGES_S[-1] * 1e3:g} ms")
    stretches = [f"{a:g}-{b:g} s" for a, b in zip(STRETCHES_S, STRETCHES_S[1:])] + [f"{STRETCHES_S[-1]:g} s-end"]
    scoring = ["| flight | every sample | at the fixes | RMSE by time since the fix: " + " / ".join(gaps) +
               " | ratio per stretch: " + " / ".join(stretches) + " |", "|---|---|---|---|---|"]
    moved_names = [f"GPS stamps {s * 1e3:+g} ms" for s in TIMING_SHIFTS_S]
    moved_names += [f"{key.split('_')[0]} white noise × {scale:g}" for key, scales in NOISE_SCALES.items() for scale in scales]
    moved = ["| flight | as imported | " + " | ".join(moved_names) + " |", "|---" * (len(moved_names) + 2) + "|"]
    lo, hi = DEFAULT_BAND_HZ
    floors = [f"| flight | accelerometer {lo:g}-{hi:g} Hz, per axis | vehicle file | gyroscope {lo:g}-{hi:g} Hz, per axis | vehicle file |",
              "|---|---|---|---|---|"]
    low = ["| flight | " + " | ".join(f"accelerometer error {a:g}-{b:g} Hz, per axis" for a, b in LOW_BANDS_HZ)
           + " | its mean (the bias) | vehicle file |", "|---" * (len(LOW_BANDS_HZ) + 3) + "|"]
    all_seeds = " / ".join(str(x) for x in (GPS_SEED, *OTHER_GPS_SEEDS))
    seeds = [f"| flight | every sample, GPS seed {all_seeds} | mean (range) | ratio per stretch, mean over the seeds: "
             + " / ".join(stretches) + f" | {stretches[0]} per seed |", "|---|---|---|---|---|"]
    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as tmp:
        for flight in flights:
            dataset = imported_flight(flight, Path(tmp))
            truth = dataset.truth()
            ratio, by_stretch, result, error = _ratio_and_stretches(dataset)
            inside = aligned_position_errors(result.trajectory, dataset)[0]
            t = truth.t_ns[inside]
            fix_t, fix_error = _gps_errors(dataset)
            at_fix = np.array([np.interp(fix_t, t, error[:, c]) for c in range(3)]).T
            ratio_at_fixes = float(np.sqrt(np.mean(np.sum(at_fix**2, axis=1)) / np.mean(np.sum(fix_error**2, axis=1))))
            by_gap = rmse_by_gap(t, error, dataset.gps().t_ns)
            scoring.append(f"| {flight.name} | {ratio:.3f} | {ratio_at_fixes:.3f} | "
                           + " / ".join(_fmt(g and g * 100, ".2f") for g in by_gap) + " cm | "
                           + " / ".join(_fmt(s, ".3f") for s in by_stretch) + " |")
            noise = dataset.calibration.imu.noise
            gps = dataset.gps()
            vehicle_density = float(np.max(noise.accel_noise_density))  # one vehicle file: the same on every flight
            fix_sigmas = float(np.median(gps.sigma_h)), float(np.median(gps.sigma_v))
            figures = [_ratio(dataset, {"calibration": {"gps": {"time_offset_s": s}}})[0] for s in TIMING_SHIFTS_S]
            figures += [_ratio(dataset, {"estimator": {"imu": {"noise": {key: float(np.max(getattr(noise, key))) * scale}}}})[0]
                        for key, scales in NOISE_SCALES.items() for scale in scales]
            moved.append(f"| {flight.name} | {ratio:.3f} | " + " | ".join(f"{f:.3f}" for f in figures) + " |")
            rows.append(Row(f"{flight.name}: position / GPS, every sample", ratio, "ratio"))
            rows.append(Row(f"{flight.name}: position / GPS, at the fixes", ratio_at_fixes, "ratio",
                            "scored as the GTSAM reference scores itself"))
            rows += [Row(f"{flight.name}: position / GPS, {name}", f, "ratio") for name, f in zip(moved_names, figures)]
            imu = dataset.imu()
            flying = imu.t_ns >= truth.t_ns[0] + SCORE_FROM_S * 1e9
            rate = 1e9 / float(np.median(np.diff(imu.t_ns)))
            accel, gyro = vibration_floor(imu.accel[flying], rate), vibration_floor(imu.gyro[flying], rate)
            floors.append(f"| {flight.name} | {' / '.join(f'{a:.3f}' for a in accel)} m/s²/√Hz | "
                          f"{np.max(noise.accel_noise_density):.3f} | {' / '.join(f'{g:.4f}' for g in gyro)} rad/s/√Hz | "
                          f"{np.max(noise.gyro_noise_density):.4f} |")
            rows.append(Row(f"{flight.name}: accelerometer vibration floor (RMS of axes)", float(np.sqrt(np.mean(accel**2))),
                            "m/s²/√Hz", f"{lo:g}-{hi:g} Hz; vehicle file {np.max(noise.accel_noise_density):g}"))
            if truth.q is not None:
                low.append(_low_band_line(flight.name, dataset, rows))
            draws = [(ratio, by_stretch)]
            for seed in OTHER_GPS_SEEDS:
                redrawn = imported_flight(flight, Path(tmp) / f"seed{seed}", seed=seed)
                draws.append(_ratio_and_stretches(redrawn)[:2])
            mean, least, most, stretch_means = over_draws(draws)
            seeds.append(f"| {flight.name} | " + " / ".join(f"{r:.3f}" for r, _ in draws) + f" | {mean:.3f} ({least:.3f}-{most:.3f}) | "
                         + " / ".join(_fmt(s, ".3f") for s in stretch_means) + " | "
                         + " / ".join(_fmt(s[0], ".3f") for _, s in draws) + " |")
            rows.append(Row(f"{flight.name}: position / GPS, mean over {len(draws)} draws of the GPS's noise", mean, "ratio",
                            f"seeds {GPS_SEED}, {', '.join(map(str, OTHER_GPS_SEEDS))}: {least:.3f}-{most:.3f}"))
    bound = ["| white acceleration density | at the fixes | over the interval |", "|---|---|---|"]
    for density in sorted({vehicle_density, *FLOOR_DENSITIES}, reverse=True):
        at, over = steady_state_ratio(density, GPS_RATE_HZ, *fix_sigmas)
        bound.append(f"| {density:g} m/s²/√Hz | {at:.3f} | {over:.3f} |")
        rows.append(Row(f"linear filter's floor at {density:g} m/s²/√Hz, over the interval", over, "ratio"))
    for line in scoring + [""] + seeds + [""] + moved + [""] + bound + [""] + floors + [""] + low:
        echo("  " + line)
    return rows
