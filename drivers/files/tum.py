"""Trajectories as files: TUM (``t x y z qx qy qz qw``, seconds) out; TUM or EuRoC CSV in.

TUM is what ``evo`` and most SLAM tools read, so estimates are written in it. For evaluation
``read_tum`` also takes EuRoC ground truth (17 columns) and Leica position-only CSVs, so any
reference the user has can be compared with. Values are returned as stored: the caller knows
which frame the file is in.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vtolpose.drivers.files.csvio import NS_PER_S, read_numeric_csv, seconds_text

TUM_HEADER = "# timestamp[s] tx ty tz qx qy qz qw"
_MAX_QUAT_NORM_ERROR = 1e-3


_ROW = " ".join(["%.9f"] * 7)


def tum_line(t_ns: int, values: tuple[float, ...] | list[float]) -> str:
    """One TUM line (no newline): exact seconds, then ``tx ty tz qx qy qz qw`` (finite; -0.0 written as 0)."""
    return f"{seconds_text(t_ns)} {_ROW % tuple(v + 0.0 for v in values)}"


def write_tum(path: str | Path, t_ns: np.ndarray, p: np.ndarray, q_wxyz: np.ndarray) -> None:
    """Write poses (world position, body→world quaternion w-first) as TUM with exact 9-decimal seconds."""
    t_ns = np.asarray(t_ns, dtype=np.int64).reshape(-1)
    q_xyzw = np.asarray(q_wxyz, dtype=float).reshape(-1, 4)[:, [1, 2, 3, 0]]
    values = np.hstack([np.asarray(p, dtype=float).reshape(-1, 3), q_xyzw])
    if values.shape[0] != t_ns.size:
        raise ValueError(f"write_tum: {t_ns.size} times but {values.shape[0]} poses")
    if not np.all(np.isfinite(values)):
        raise ValueError("write_tum: refusing to write non-finite poses")
    lines = [TUM_HEADER, *(tum_line(t, v) for t, v in zip(t_ns.tolist(), values.tolist()))]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8", newline="\n")


def _unit_quaternions(q: np.ndarray, t_ns: np.ndarray, path: Path) -> np.ndarray:
    norm = np.linalg.norm(q, axis=1)
    if np.any(np.abs(norm - 1.0) > _MAX_QUAT_NORM_ERROR):
        i = int(np.argmax(np.abs(norm - 1.0)))
        when = seconds_text(int(t_ns[i]))
        raise ValueError(f"{path}: quaternion of norm {norm[i]:.6f} at t={when} s (expected unit)")
    return q / norm[:, None]


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(t_ns, p, q_wxyz)`` from a TUM file, a 17-column EuRoC truth CSV, or a 4-column position CSV.

    The kind is told by the first non-blank line: commas mean EuRoC CSV (its column count says
    which), otherwise TUM. ``q`` is None for position-only files.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: trajectory file not found")
    with path.open(encoding="utf-8-sig", errors="replace") as f:
        first = next((line.strip() for line in f if line.strip()), "")
    if not first:
        raise ValueError(f"{path}: empty trajectory file")
    if "," in first:
        columns = len(first.lstrip("#").split(","))
        if columns == 17:
            data = read_numeric_csv(path, 16, header="EuRoC ground truth: timestamp, p xyz, q wxyz, v, biases")
            return data.t_ns, data.values[:, :3], _unit_quaternions(data.values[:, 3:7], data.t_ns, path)
        if columns == 4:
            data = read_numeric_csv(path, 3, header="timestamp [ns], p xyz [m]")
            return data.t_ns, data.values, None
        raise ValueError(f"{path}: CSV with {columns} columns; expected EuRoC ground truth (17) or positions (4)")
    data = read_numeric_csv(path, 7, header="TUM: t[s] x y z qx qy qz qw", delimiter=None,
                            time_unit_ns=NS_PER_S, require_header=False)
    if data.t_ns.size == 0:
        raise ValueError(f"{path}: no valid TUM lines (expected 't x y z qx qy qz qw')")
    q = data.values[:, [6, 3, 4, 5]]
    return data.t_ns, data.values[:, :3], _unit_quaternions(q, data.t_ns, path)
