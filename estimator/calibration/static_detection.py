"""Static stretches in an IMU record: where the vehicle stands still, for calibration.

A calibration needs rest, not quiet: on a pad with the engine idling the IMU vibrates, yet
the vehicle neither turns nor tilts. So a chunk of samples counts as static when its *means*
(gyro rate, specific force) agree with those of the chunks just before it — a rotation or a
tilt of a fraction of a degree per second shows up there — and its scatter stays below loose
limits that only real handling or flight exceeds. Consecutive static chunks form a stretch; one
chunk is trimmed at each end, where motion starts or stops inside it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


class NoStaticStretchError(ValueError):
    """The record has no static stretch long enough; the message says what to record instead."""


@dataclass(frozen=True, slots=True)
class StaticOptions:
    chunk_s: float = 1.0
    min_duration_s: float = 10.0
    gyro_mean_tol: float = 0.005  # rad/s between a chunk's mean and its neighbours' (≈ 0.3 °/s)
    accel_mean_tol: float = 0.05  # m/s² (≈ 0.3° of tilt)
    gyro_std_max: float = 0.1  # rad/s per axis: more is handling or flight, not engine vibration
    accel_std_max: float = 1.0  # m/s² per axis
    gravity: float = 9.80665  # nominal g
    gravity_tolerance: float = 0.5  # m/s² allowed between |mean specific force| and g
    neighbours: int = 5  # chunks whose mean a new chunk is compared with
    trim_chunks: int = 1


@dataclass(frozen=True, slots=True)
class StaticStretch:
    """Samples ``[start, stop)`` of the record, and their times."""

    start: int
    stop: int
    t0_ns: int
    t1_ns: int

    @property
    def duration_s(self) -> float:
        return (self.t1_ns - self.t0_ns) * 1e-9


def _chunk_stats(t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray, chunk_s: float):
    """Boundaries, means and standard deviations of consecutive chunks of ``chunk_s`` seconds."""
    edges_t = np.arange(t_ns[0], t_ns[-1] + 1, int(chunk_s * 1e9), dtype=np.int64)
    edges = np.searchsorted(t_ns, edges_t)
    edges = np.unique(np.append(edges, len(t_ns)))
    counts = np.diff(edges)
    keep = counts >= 2
    data = np.hstack([gyro, accel])
    sums = np.add.reduceat(data, edges[:-1], axis=0)
    sq = np.add.reduceat(data * data, edges[:-1], axis=0)
    mean = sums / counts[:, None]
    std = np.sqrt(np.maximum(sq / counts[:, None] - mean**2, 0.0) * counts[:, None] / np.maximum(counts - 1, 1)[:, None])
    return edges[:-1][keep], edges[1:][keep], counts[keep], mean[keep], std[keep]


def find_static_stretches(
    t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray, options: StaticOptions = StaticOptions()
) -> list[StaticStretch]:
    """All static stretches of at least ``min_duration_s``, longest first."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    if len(t_ns) < 2:
        return []
    starts, stops, counts, mean, std = _chunk_stats(t_ns, np.asarray(gyro, float), np.asarray(accel, float), options.chunk_s)
    quiet = (np.all(std[:, :3] <= options.gyro_std_max, axis=1) & np.all(std[:, 3:] <= options.accel_std_max, axis=1)
             & (np.abs(np.linalg.norm(mean[:, 3:], axis=1) - options.gravity) <= options.gravity_tolerance))
    # A chunk mean scatters by std/√n on its own: never demand agreement tighter than 4 of those.
    tol = np.maximum(np.r_[[options.gyro_mean_tol] * 3, [options.accel_mean_tol] * 3], 4.0 * std / np.sqrt(counts)[:, None])
    runs: list[tuple[int, int]] = []
    run_start = None
    for k in range(len(starts)):
        joins = quiet[k] and run_start is not None and starts[k] == stops[k - 1]
        if joins:
            ref = mean[max(run_start, k - options.neighbours):k].mean(axis=0)
            joins = bool(np.all(np.abs(mean[k] - ref) <= tol[k]))
        if not joins:
            if run_start is not None:
                runs.append((run_start, k))
            run_start = k if quiet[k] else None
    if run_start is not None:
        runs.append((run_start, len(starts)))
    out = []
    for first, end in runs:
        first, last = first + options.trim_chunks, end - 1 - options.trim_chunks
        if last < first:
            continue
        a, b = int(starts[first]), int(stops[last])
        stretch = StaticStretch(a, b, int(t_ns[a]), int(t_ns[b - 1]))
        if stretch.duration_s >= options.min_duration_s:
            out.append(stretch)
    return sorted(out, key=lambda s: -s.duration_s)


def reject_moving(
    stretches: list[StaticStretch], fix_t_ns: np.ndarray, fix_p: np.ndarray, max_speed: float = 0.2
) -> tuple[list[StaticStretch], list[tuple[StaticStretch, float]]]:
    """Split stretches into those the position fixes confirm as rest and those they show moving.

    An IMU cannot tell rest from straight, steady flight (no rotation, specific force = g); a
    position track can. A stretch with fewer than 3 fixes is kept (nothing contradicts it).
    """
    kept, moving = [], []
    fix_t_ns = np.asarray(fix_t_ns, dtype=np.int64)
    for s in stretches:
        inside = (fix_t_ns >= s.t0_ns) & (fix_t_ns <= s.t1_ns)
        if np.count_nonzero(inside) < 3:
            kept.append(s)
            continue
        t = (fix_t_ns[inside] - s.t0_ns) * 1e-9
        velocity = np.polyfit(t, np.asarray(fix_p, float)[inside], 1)[0]
        speed = float(np.linalg.norm(velocity))
        if speed <= max_speed:
            kept.append(s)
        else:
            moving.append((s, speed))
    return kept, moving


def rest_advice(min_duration_s: float) -> str:
    """What to record, consistent with the shortest stretch asked for (``--min-static``)."""
    return (f"Record the vehicle standing still on level ground, untouched, for at least {min_duration_s:g} s "
            f"(the shortest stretch asked for); 30 s or more gives a steadier gyro bias, minutes the Allan noise "
            f"figures, an hour or more the bias random walk. A simulated record: vtolpose simulate --rest S")


def require_static_stretch(
    t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray, options: StaticOptions = StaticOptions()
) -> StaticStretch:
    """The longest static stretch, or an error saying what was seen and what to record."""
    found = find_static_stretches(t_ns, gyro, accel, options)
    if found:
        return found[0]
    longest = find_static_stretches(t_ns, gyro, accel, replace(options, min_duration_s=0.0))
    seen = f"the longest is {longest[0].duration_s:.1f} s" if longest else "none at all"
    raise NoStaticStretchError(
        f"no static stretch of at least {options.min_duration_s:g} s in the IMU record ({seen}; a stretch must not "
        f"turn by more than {options.gyro_mean_tol:g} rad/s or tilt by more than {options.accel_mean_tol:g} m/s^2 "
        f"between {options.chunk_s:g} s chunks). {rest_advice(options.min_duration_s)}")
