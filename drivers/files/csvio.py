"""Tolerant reading and deterministic writing of timestamped numeric tables (ASL/EuRoC CSV, TUM).

Real logs are messy (spreadsheets, truncated writes, trailing notes), so a bad *data* line is
skipped and counted, with one warning per file naming the first offender; a bad *header* or a
missing file is an error, because then nothing in the file can be trusted. Timestamps are
integer nanoseconds but may be written in scientific notation: they are parsed exactly with
``decimal`` (float64 is off by up to 128 ns at 1.4e18).
"""

from __future__ import annotations

import ctypes
import io
import logging
from decimal import Decimal
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np

log = logging.getLogger(__name__)

_INT64_MAX = 2**63 - 1
NS_PER_S = 1_000_000_000


class CsvData(NamedTuple):
    """Rows that parsed: times (int64 ns), values (float64, rows × columns), lines skipped."""

    t_ns: np.ndarray
    values: np.ndarray
    skipped: int


def parse_time_ns(text: str, unit_ns: int = 1) -> int:
    """Exact integer nanoseconds from ``text`` counted in units of ``unit_ns`` ns.

    With ``unit_ns == 1`` the value must be integral (``1.40363657975856E+018`` is); in larger
    units (seconds: ``unit_ns = 1e9``) it is rounded to the nearest nanosecond.
    Raises ValueError on anything else.
    """
    text = text.strip()
    if unit_ns == 1 and text.isascii() and text.isdigit():  # isdigit alone also takes '²', which int() refuses
        value = int(text)
    else:
        try:
            number = Decimal(text) * unit_ns
        except ArithmeticError:  # InvalidOperation for text, Overflow for exponents beyond decimal's range
            raise ValueError(f"not a number: {text!r}") from None
        if not number.is_finite():
            raise ValueError(f"not finite: {text!r}")
        if number and number.adjusted() > 19:  # beyond int64 (checked before building a huge integer)
            raise ValueError(f"time out of int64 range: {text!r}")
        integral = number.to_integral_value()
        if unit_ns == 1 and number != integral:
            raise ValueError(f"not an integer nanosecond time: {text!r}")
        value = int(integral)
    if abs(value) > _INT64_MAX:
        raise ValueError(f"time out of int64 range: {text!r}")
    return value


def _split(line: str, delimiter: str | None) -> list[str]:
    return line.split(delimiter) if delimiter is not None else line.split()


def _read_clean(text: str, n_values: int) -> CsvData | None:
    """A well-formed table (a ``#`` header of ``n_values + 1`` columns, then only data lines with
    integer times in increasing order and finite values) through numpy's C parser, several times
    faster than the line-by-line reader; None when anything is off, so that reader takes over and
    counts what it skips. The two give the same arrays for every table this one accepts."""
    if "\r" in text or "\n\n" in text.rstrip("\n") or not text.startswith("#"):
        return None
    header, _, body = text.partition("\n")
    if "#" in body or len(header[1:].split(",")) != n_values + 1 or not body.strip():
        return None
    try:  # int64 times: digits with an optional sign, as the line-by-line reader takes them exactly
        table = np.loadtxt(io.StringIO(body), delimiter=",", comments=None, ndmin=1,
                           dtype={"names": [f"c{i}" for i in range(n_values + 1)], "formats": ["i8"] + ["f8"] * n_values})
    except ValueError:
        return None
    t_ns = table["c0"]
    if len(t_ns) != body.rstrip("\n").count("\n") + 1:  # a blank line the parser passed over
        return None
    values = np.column_stack([table[f"c{i + 1}"] for i in range(n_values)])
    if np.any(np.diff(t_ns) <= 0) or not np.all(np.isfinite(values)):
        return None
    return CsvData(np.ascontiguousarray(t_ns), values, 0)


def read_numeric_csv(
    path: str | Path,
    n_values: int,
    *,
    header: str = "",
    delimiter: str | None = ",",
    time_unit_ns: int = 1,
    require_header: bool = True,
    in_order: bool = True,
) -> CsvData:
    """Read ``time, v1..vn`` lines; malformed or out-of-order data lines are skipped and counted.

    ``header`` is the expected header text, only used to make error messages concrete.
    Lines starting with ``#`` are comments; with ``require_header`` the first line must be one
    with ``n_values + 1`` columns (the column header). A data line is kept when it
    has exactly ``n_values + 1`` fields, all numeric and finite, and a time later than every
    line before it. ``in_order=False`` keeps the lines that parse in file order, whatever their times
    (the caller undoes clock steps first, then drops what is still out of order: :func:`in_time_order`).
    """
    path = Path(path)
    try:
        return _read_numeric_csv(path, n_values, header, delimiter, time_unit_ns, require_header, in_order)
    finally:
        if path.is_file() and path.stat().st_size > _TRIM_AFTER_BYTES:
            return_freed_heap()


_TRIM_AFTER_BYTES = 1 << 20  # parsing a table this large leaves megabytes of freed heap behind


def return_freed_heap() -> None:
    """Hand the heap pages freed by parsing back to the operating system. glibc keeps them for reuse
    otherwise: an hour's GPS file (36,000 lines) left 14 MB resident. Nothing to do without glibc."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc (musl, macOS): its allocator decides, nothing to ask
        return


def _read_numeric_csv(path: Path, n_values: int, header: str, delimiter: str | None, time_unit_ns: int,
                      require_header: bool, in_order: bool = True) -> CsvData:
    n_fields = n_values + 1
    expected = f"{n_fields} columns" + (f" ({header})" if header else "")
    try:
        text = path.read_text(encoding="utf-8-sig", errors="replace")
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: file not found (expected a table of {expected})") from None
    clean = _read_clean(text, n_values) if delimiter == "," and time_unit_ns == 1 else None
    if clean is not None:
        return clean
    lines = text.splitlines()

    if require_header:
        first = next((i for i, ln in enumerate(lines) if ln.strip()), None)
        if first is None or not lines[first].lstrip().startswith("#"):
            raise ValueError(f"{path}: missing '#' header line, expected {expected}")
        found = len(_split(lines[first].lstrip()[1:], delimiter))
        if found != n_fields:
            raise ValueError(f"{path}: header line {first + 1} has {found} columns, expected {expected}")

    times: list[int] = []
    rows: list[list[float]] = []
    line_numbers: list[int] = []
    bad: list[tuple[int, str, str]] = []  # (line number, text, reason)
    for number, line in enumerate(lines, start=1):
        stripped = line.strip()
        if stripped.startswith("#"):
            continue
        fields = _split(stripped, delimiter)
        if len(fields) != n_fields:
            bad.append((number, line, f"{len(fields)} fields instead of {n_fields}"))
            continue
        try:
            t = parse_time_ns(fields[0], time_unit_ns)
            row = [float(f) for f in fields[1:]]
        except ValueError as exc:
            bad.append((number, line, str(exc)))
            continue
        times.append(t)
        rows.append(row)
        line_numbers.append(number)

    t_ns = np.array(times, dtype=np.int64)
    values = np.array(rows, dtype=np.float64).reshape(len(rows), n_values)
    keep = np.all(np.isfinite(values), axis=1)
    for i in np.flatnonzero(~keep):
        bad.append((line_numbers[i], lines[line_numbers[i] - 1], "non-finite value"))
    # A line must be later than every valid line before it (prefix maximum of their times).
    if t_ns.size and in_order:
        valid_t = np.where(keep, t_ns, np.iinfo(np.int64).min)
        earlier_max = np.concatenate([[np.iinfo(np.int64).min], np.maximum.accumulate(valid_t)[:-1]])
        in_order = t_ns > earlier_max
        for i in np.flatnonzero(keep & ~in_order):
            bad.append((line_numbers[i], lines[line_numbers[i] - 1], "time not after the previous line"))
        keep &= in_order

    if bad:
        number, line, reason = min(bad)
        log.warning(
            "%s: skipped %d malformed line(s); first is line %d (%s): %r",
            path, len(bad), number, reason, line[:120],
        )
    return CsvData(t_ns[keep], values[keep], len(bad))


def in_time_order(t_ns: np.ndarray) -> np.ndarray:
    """Which rows are later than every row before them (the order check of :func:`read_numeric_csv`)."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    if t_ns.size == 0:
        return np.ones(0, dtype=bool)
    earlier_max = np.concatenate([[np.iinfo(np.int64).min], np.maximum.accumulate(t_ns)[:-1]])
    return t_ns > earlier_max


def format_rows(t_ns: np.ndarray, values: np.ndarray, formats: Sequence[str], delimiter: str = ",") -> list[str]:
    """Lines ``t,v1,..,vn`` with one printf format per value column: same data, same bytes."""
    values = np.asarray(values, dtype=np.float64).reshape(len(t_ns), len(formats))
    if not np.all(np.isfinite(values)):
        raise ValueError("refusing to write non-finite values")
    row_format = delimiter.join(formats)
    # +0.0 turns -0.0 into 0.0, so a sign bit never changes the bytes.
    times = np.asarray(t_ns, dtype=np.int64).tolist()
    return [f"{t}{delimiter}{row_format % tuple(row)}" for t, row in zip(times, (values + 0.0).tolist())]


def write_numeric_csv(
    path: str | Path, header: str, t_ns: np.ndarray, values: np.ndarray, formats: Sequence[str]
) -> None:
    """Write a ``#``-headed CSV of integer times and formatted values, creating the folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [header, *format_rows(t_ns, values, formats)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8", newline="\n")


def seconds_text(t_ns: int) -> str:
    """Exact decimal seconds with 9 decimals from integer nanoseconds (no float rounding)."""
    sign = "-" if t_ns < 0 else ""
    whole, frac = divmod(abs(int(t_ns)), NS_PER_S)
    return f"{sign}{whole}.{frac:09d}"

