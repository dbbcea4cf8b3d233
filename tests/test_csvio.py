"""Tolerant CSV reading: exact nanosecond times, counted skips with one warning, clear errors."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from vtolpose.drivers.files.csvio import parse_time_ns, read_numeric_csv, seconds_text, write_numeric_csv

HEADER = "#timestamp [ns],a,b,c"


def write(path: Path, *lines: str) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


def test_clean_file_reads_exact_values(tmp_path: Path) -> None:
    f = write(tmp_path / "d.csv", HEADER, "1403636579758560001,1.5,-2,3e-3", "1403636579763560001,4,5,6")
    data = read_numeric_csv(f, 3)
    assert data.t_ns.dtype == np.int64 and data.values.dtype == np.float64
    assert data.t_ns.tolist() == [1403636579758560001, 1403636579763560001]
    np.testing.assert_array_equal(data.values, [[1.5, -2.0, 0.003], [4.0, 5.0, 6.0]])
    assert data.skipped == 0


def test_scientific_notation_times_are_exact() -> None:
    # float64 steps are 256 ns at 1.4e18: a parser going through it would fail these.
    assert int(float("1.403636579758560001E+18")) != 1403636579758560001
    assert int(float("1.40363657975857E+018")) != 1403636579758570000
    assert parse_time_ns("1.40363657975857E+018") == 1403636579758570000
    assert parse_time_ns("1.40363657975856E+018") == 1403636579758560000
    assert parse_time_ns("1.403636579758560001E+18") == 1403636579758560001
    assert parse_time_ns(" 42 ") == 42
    assert parse_time_ns("1403636579.758560001", unit_ns=1_000_000_000) == 1403636579758560001


@pytest.mark.parametrize("text", ["", "abc", "12.5", "nan", "inf", "1e400"])
def test_bad_times_raise(text: str) -> None:
    with pytest.raises(ValueError):
        parse_time_ns(text)


def test_malformed_lines_are_skipped_counted_and_warned_once(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    f = write(
        tmp_path / "d.csv",
        HEADER,
        "100,1,2,3",
        "200,1,2",            # line 3: too few fields
        "300,1,,3",           # empty field
        "400,1,x,3",          # text
        "500,1,nan,3",        # not finite
        "600,inf,2,3",        # not finite
        "50,1,2,3",           # earlier than a previous line
        "1.7e3,1,2,3",        # fine: scientific notation integer
        ",,,",
        "Step: 0.005 = 1/200,,,",
        "# a comment is not a data line",
        "2000,7,8,9",
    )
    with caplog.at_level(logging.WARNING, logger="vtolpose.drivers.files.csvio"):
        data = read_numeric_csv(f, 3)
    assert data.t_ns.tolist() == [100, 1700, 2000]
    assert data.skipped == 8
    assert not np.any(np.isnan(data.values))
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    message = warnings[0].getMessage()
    assert "skipped 8" in message and "line 3" in message and "'200,1,2'" in message and "d.csv" in message


def test_missing_file_names_it(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nothere.csv"):
        read_numeric_csv(tmp_path / "nothere.csv", 3)


def test_header_with_missing_column_is_an_error(tmp_path: Path) -> None:
    f = write(tmp_path / "short.csv", "#timestamp [ns],a,b", "1,2,3")
    with pytest.raises(ValueError, match=r"short\.csv.*3 columns, expected 4 columns \(#timestamp \[ns\],a,b,c\)"):
        read_numeric_csv(f, 3, header=HEADER)


def test_missing_header_is_an_error(tmp_path: Path) -> None:
    f = write(tmp_path / "nohead.csv", "1,2,3,4")
    with pytest.raises(ValueError, match=r"nohead\.csv: missing '#' header"):
        read_numeric_csv(f, 3)


def test_whitespace_delimited_seconds_without_header(tmp_path: Path) -> None:
    f = write(tmp_path / "t.txt", "1403636579.758560001 1 2 3", "  1403636579.8 4 5 6  ")
    data = read_numeric_csv(f, 3, delimiter=None, time_unit_ns=1_000_000_000, require_header=False)
    assert data.t_ns.tolist() == [1403636579758560001, 1403636579800000000]


def test_forty_thousand_scientific_lines_are_read_exactly(tmp_path: Path) -> None:
    t = 1403636579758560000 + 5_000_000 * np.arange(40_000, dtype=np.int64)
    values = "-0.0991347015,0.1473057889,0.0272271363,8.1476917083,-0.37592158,-2.40262925"
    lines = [f"{ti / 1e18:.14f}E+018,{values}" for ti in t]
    f = write(tmp_path / "big.csv", "#t,a,b,c,d,e,f", *lines)
    data = read_numeric_csv(f, 6)
    assert data.t_ns.size == 40_000 and data.skipped == 0
    assert np.all(np.diff(data.t_ns) == 5_000_000)


def test_write_is_deterministic_and_round_trips(tmp_path: Path) -> None:
    t = np.array([1, 2, 1403636579758560001], dtype=np.int64)
    v = np.array([[0.1, -0.0, 1e-7], [2.0, 3.0, 4.0], [-1.25, 0.5, 9.80665]])
    write_numeric_csv(tmp_path / "a.csv", HEADER, t, v, ["%.9f"] * 3)
    write_numeric_csv(tmp_path / "b.csv", HEADER, t, v.copy(), ["%.9f"] * 3)
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()
    assert b"-0.000000000" not in (tmp_path / "a.csv").read_bytes()
    back = read_numeric_csv(tmp_path / "a.csv", 3)
    assert back.t_ns.tolist() == t.tolist()
    np.testing.assert_allclose(back.values, v, atol=5e-10)


def test_write_refuses_non_finite(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="non-finite"):
        write_numeric_csv(tmp_path / "a.csv", HEADER, np.array([1]), np.array([[np.nan, 0, 0]]), ["%.3f"] * 3)


def test_seconds_text_is_exact() -> None:
    assert seconds_text(1403636579758560001) == "1403636579.758560001"
    assert seconds_text(5) == "0.000000005"
    assert seconds_text(-1_500_000_000) == "-1.500000000"


CLEAN_AND_MESSY = {
    "clean": [HEADER, "1,1.5,-2,3e-3", "2,4,5,6", "1403636579758560001,7, 8 ,9"],
    "comment in the body": [HEADER, "1,1,2,3", "# a note", "2,4,5,6"],
    "trailing note": [HEADER, "1,1,2,3 # note", "2,4,5,6"],
    "blank line": [HEADER, "1,1,2,3", "", "2,4,5,6"],
    "scientific time": [HEADER, "1.4E+1,1,2,3", "20,4,5,6"],
    "fractional time": [HEADER, "1.5,1,2,3", "20,4,5,6"],
    "time out of order": [HEADER, "5,1,2,3", "4,4,5,6", "6,7,8,9"],
    "non-finite value": [HEADER, "1,nan,2,3", "2,4,5,6"],
    "empty fields": [HEADER, "1,1,2,3", ",,,"],
    "underscore digits": [HEADER, "1_0,1,2,3", "20,1_5,5,6"],
    "beyond int64": [HEADER, "9223372036854775808,1,2,3", "9223372036854775809,4,5,6"],
    "signed time": [HEADER, "-5,1,2,3", "+7,4,5,6"],
}


@pytest.mark.parametrize("case", sorted(CLEAN_AND_MESSY))
def test_fast_path_and_line_reader_agree(case: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Clean tables go through numpy's parser, anything else through the line reader: same result."""
    import vtolpose.drivers.files.csvio as csvio
    f = write(tmp_path / "d.csv", *CLEAN_AND_MESSY[case])
    try:
        fast = read_numeric_csv(f, 3)
    except ValueError as exc:
        fast = exc
    monkeypatch.setattr(csvio, "_read_clean", lambda text, n_values: None)
    try:
        slow = read_numeric_csv(f, 3)
    except ValueError as exc:
        slow = exc
    if isinstance(slow, Exception):
        assert str(fast) == str(slow)
        return
    assert fast.t_ns.dtype == slow.t_ns.dtype and fast.values.dtype == slow.values.dtype
    np.testing.assert_array_equal(fast.t_ns, slow.t_ns)
    np.testing.assert_array_equal(fast.values, slow.values)
    assert fast.skipped == slow.skipped


def test_clean_table_takes_the_fast_path(tmp_path: Path) -> None:
    import vtolpose.drivers.files.csvio as csvio
    text = "\n".join([HEADER, "1,1.5,-2,3e-3", "2,4,5,6"]) + "\n"
    clean = csvio._read_clean(text, 3)
    assert clean is not None and clean.t_ns.tolist() == [1, 2] and clean.skipped == 0
    assert csvio._read_clean(text.replace("2,4,5,6", "2,4,5,6 # late note"), 3) is None
