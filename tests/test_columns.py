"""make_room: the live rows kept in order, slid to the front where there is room, else in arrays twice as long."""

import numpy as np

from vtolpose.estimator.core.columns import make_room


def _columns(size: int) -> tuple[np.ndarray, np.ndarray]:
    return np.arange(size, dtype=np.int64), np.arange(3 * size, dtype=float).reshape(size, 3)


def test_rows_slide_to_the_front_of_the_same_arrays_where_they_fit():
    t, rows = _columns(16)
    (t2, rows2), start, end = make_room((t, rows), 10, 16, 2)  # 6 live rows, 2 more: within half of 16
    assert (start, end) == (0, 6) and t2 is t and rows2 is rows
    assert t2[:6].tolist() == list(range(10, 16)) and rows2[:6].tolist() == np.arange(30, 48).reshape(6, 3).tolist()


def test_rows_are_copied_into_longer_arrays_when_they_do_not_fit():
    t, rows = _columns(16)
    (t2, rows2), start, end = make_room((t, rows), 0, 16, 1)  # full from the front: twice the room
    assert (start, end) == (0, 16) and len(t2) == len(rows2) == 32 and t2.dtype == np.int64 and rows2.shape[1] == 3
    assert np.array_equal(t2[:16], t) and np.array_equal(rows2[:16], rows)
    (t3, _), _, _ = make_room((t, rows), 0, 16, 40)  # more than twice: as long as needed
    assert len(t3) == 56


def test_a_window_nearly_as_long_as_its_arrays_copies_few_rows_per_row_added():
    # A sliding window of a steady length just under its arrays' (15 of 16): each row added lets one go.
    columns, start, end = _columns(16), 0, 15
    copied = 0
    for _ in range(2000):
        if end == len(columns[0]):
            copied += end - start
            columns, start, end = make_room(columns, start, end, 1)
        end += 1
        start += 1
    assert copied / 2000 <= 2.0  # amortised, not the whole window again every other row
