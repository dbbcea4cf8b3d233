"""The fleet table: one row per flight, as Parquet (typed, for analysis) and CSV (for a spreadsheet).

Both files are written under a temporary name and renamed, so a reader never sees half a table.
"""

from __future__ import annotations

import csv
import os
from pathlib import Path
from typing import Any

# (column, Arrow type name): the table's columns in order; a figure a flight does not have is empty.
COLUMNS: tuple[tuple[str, str], ...] = (
    ("flight", "string"), ("status", "string"), ("error", "string"), ("input", "string"), ("kind", "string"),
    ("duration_s", "float64"), ("distance_m", "float64"), ("resets", "int64"), ("sensors", "string"),
    ("gps_received", "int64"), ("gps_rejected", "int64"),
    ("quality_mean", "float64"), ("quality_usable_fraction", "float64"), ("quality_bin_s", "float64"),
    ("quality_over_time", "list<float64>"),
    ("truth", "string"), ("position_rmse_m", "float64"), ("smoothed_position_rmse_m", "float64"),
    ("attitude_rmse_deg", "float64"),
    ("map_cells", "int64"), ("map_area_m2", "float64"), ("map_coverage", "float64"), ("volume_m3", "float64"),
    ("true_volume_m3", "float64"), ("volume_error_m3", "float64"), ("volume_error_percent", "float64"),
    ("map_height_rmse_m", "float64"), ("map_height_bias_m", "float64"),
    ("pose_height_error_cells_m", "float64"), ("pose_height_error_returns_m", "float64"),
    ("notes", "int64"), ("wall_s", "float64"), ("host", "string"), ("pid", "int64"),
)
NAMES = tuple(name for name, _ in COLUMNS)


def _schema():
    import pyarrow as pa

    types = {"string": pa.string(), "float64": pa.float64(), "int64": pa.int64(), "list<float64>": pa.list_(pa.float64())}
    return pa.schema([(name, types[kind]) for name, kind in COLUMNS])


def _replace(tmp: Path, path: Path) -> None:
    os.replace(tmp, path)


def write_parquet(rows: list[dict[str, Any]], path: Path) -> Path:
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pa.Table.from_pylist([{name: row.get(name) for name in NAMES} for row in rows], schema=_schema())
    tmp = path.with_name(f".{path.name}.tmp")
    pq.write_table(table, tmp)
    _replace(tmp, path)
    return path


def _cell(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, list):
        return " ".join("" if v is None else f"{v:g}" for v in value)
    return value


def write_csv(rows: list[dict[str, Any]], path: Path) -> Path:
    """The same columns; ``quality_over_time`` as its figures separated by spaces."""
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(NAMES)
        for row in rows:
            writer.writerow([_cell(row.get(name)) for name in NAMES])
    _replace(tmp, path)
    return path


def write_tables(rows: list[dict[str, Any]], out_root: Path) -> tuple[Path, Path]:
    """``fleet.parquet`` and ``fleet.csv`` in ``out_root``."""
    out_root.mkdir(parents=True, exist_ok=True)
    return write_parquet(rows, out_root / "fleet.parquet"), write_csv(rows, out_root / "fleet.csv")
