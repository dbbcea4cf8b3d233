"""Pose history: interpolation (linear position, slerp attitude), bounds, fused-over-predicted, eviction."""

import numpy as np
import pytest

from vtolpose.estimator.pose_history import OutsideHistory, PoseHistory, interpolate_rows
from vtolpose.estimator.core.rotation import quat_from_euler, rotation_angle

MS = 1_000_000


def pose_row(t_ns: int, history: PoseHistory) -> np.ndarray:
    """Constant velocity (1, 2, -0.5) m/s and constant yaw rate 0.3 rad/s: interpolation is exact."""
    t = t_ns * 1e-9
    p = np.array([1.0, 2.0, -0.5]) * t
    q = quat_from_euler(0.1, -0.05, 0.3 * t)
    return history.make_row(p, q, np.array([1.0, 2.0, -0.5]), np.array([0.0, 0.0, 0.3]), np.eye(6) * t)


def filled(span_s: float = 120.0, step_ms: int = 10, n: int = 200) -> PoseHistory:
    h = PoseHistory(span_s, initial_capacity=16)
    for k in range(1, n + 1):
        h.add_fused(k * step_ms * MS, pose_row(k * step_ms * MS, h))
    return h


def test_interpolation_between_entries_is_linear_and_slerp():
    h = filled()
    t = 1234 * MS + 567  # between the entries at 1230 and 1240 ms
    got = h.at(t)
    truth_p = np.array([1.0, 2.0, -0.5]) * t * 1e-9
    truth_q = quat_from_euler(0.1, -0.05, 0.3 * t * 1e-9)
    assert np.allclose(got.p, truth_p, atol=1e-12)
    assert np.degrees(rotation_angle(got.q, truth_q)) < 1e-9
    assert got.fused
    assert np.allclose(got.cov, np.eye(6) * t * 1e-9)


def test_exact_times_and_ends_return_the_stored_entry():
    h = filled()
    first, last = h.bounds()
    assert (first, last) == (10 * MS, 2000 * MS)
    for t in (first, 500 * MS, last):
        assert np.allclose(h.at(t).p, np.array([1.0, 2.0, -0.5]) * t * 1e-9, atol=1e-12)


@pytest.mark.parametrize("t", [10 * MS - 1, 2000 * MS + 1, -5])
def test_times_outside_raise(t):
    with pytest.raises(OutsideHistory, match="outside the history"):
        filled().at(t)
    with pytest.raises(OutsideHistory, match="empty"):
        PoseHistory(1.0).at(0)


def test_span_bounds_the_history_and_the_memory():
    h = PoseHistory(1.0, initial_capacity=16)
    for k in range(1, 20001):  # 200 s at 100 Hz into a 1 s history
        h.add_fused(k * 10 * MS, pose_row(k * 10 * MS, h))
    first, last = h.bounds()
    assert last - first <= 1_000_000_000 and len(h) == 101
    assert h.capacity <= 256  # compacted in place, not grown without end
    with pytest.raises(OutsideHistory):
        h.at(last - 1_500_000_000)


def test_fused_poses_replace_the_predictions_they_cover():
    h = filled(n=10)  # fused up to 100 ms
    for k in range(11, 16):  # predictions up to 150 ms, offset by 1 m
        row = pose_row(k * 10 * MS, h)
        row[0] += 1.0
        h.add_predicted(k * 10 * MS, row)
    assert h.bounds()[1] == 150 * MS and not h.at(145 * MS).fused
    assert h.at(125 * MS).p[0] == pytest.approx(0.125 + 1.0)
    assert h.at(105 * MS).p[0] == pytest.approx(0.105 + 0.5)  # between fused (100) and predicted (110)
    h.add_fused(130 * MS, pose_row(130 * MS, h))
    assert len(h) == 11 + 2  # predictions at 110..130 gone, 140 and 150 remain
    assert h.at(125 * MS).fused and h.at(125 * MS).p[0] == pytest.approx(0.125)
    h.add_predicted(120 * MS, pose_row(120 * MS, h))  # older than a fused pose: ignored
    assert len(h) == 13


def test_window_returns_entries_inside_bracketed_and_refuses_disjoint():
    h = filled()
    w = h.window(100 * MS, 150 * MS)
    assert w.t_ns.tolist() == [k * 10 * MS for k in range(10, 16)]
    assert w.fused.all() and w.p.shape == (6, 3) and w.q.shape == (6, 4)
    p, q = w.interpolate(np.array([105 * MS, 149 * MS]))
    assert np.allclose(p[:, 0], [0.105, 0.149])
    scan = h.window(101 * MS, 149 * MS)  # ends between entries: their neighbours come along
    assert scan.t_ns.tolist() == [k * 10 * MS for k in range(10, 16)]
    p, _ = scan.interpolate(np.array([101 * MS, 149 * MS]))
    assert np.allclose(p[:, 0], [0.101, 0.149])
    assert h.window(0, 15 * MS).t_ns.tolist() == [10 * MS, 20 * MS]  # clipped to the history at its start
    with pytest.raises(OutsideHistory, match="does not overlap"):
        h.window(3000 * MS, 4000 * MS)
    with pytest.raises(ValueError, match="before its start"):
        h.window(5, 4)


def test_interpolate_rows_takes_the_short_arc():
    q0 = np.array([1.0, 0.0, 0.0, 0.0])
    q1 = -quat_from_euler(0.0, 0.0, 0.2)  # same rotation, opposite sign
    rows = np.zeros((2, 49))
    rows[0, 3:7], rows[1, 3:7] = q0, q1
    mid = interpolate_rows(np.array([0, 10]), rows, np.array([5]))[0, 3:7]
    assert np.degrees(rotation_angle(mid, quat_from_euler(0.0, 0.0, 0.1))) < 1e-9


def smoothed_rows(h: PoseHistory, times_ms: list[int], offset: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows at ``times_ms`` moved by ``offset`` metres north, with a smaller covariance and no body rate."""
    rows = np.array([pose_row(t * MS, h) for t in times_ms])
    rows[:, 0] += offset
    rows[:, 10:13] = 0.0
    rows[:, 13:49] *= 0.25
    return np.array(times_ms, dtype=np.int64) * MS, rows


def test_smoothed_poses_replace_the_filtered_ones_over_their_span():
    h = filled(n=100)  # filtered every 10 ms up to 1 s
    t, rows = smoothed_rows(h, list(range(200, 501, 10)), 0.01)
    assert h.add_smoothed(t, rows) == 31
    assert len(h) == 100  # same times: replaced one for one
    got = h.at(350 * MS)
    assert got.kind == "smoothed" and got.fused and got.p[0] == pytest.approx(0.35 + 0.01)
    assert np.allclose(got.cov, np.eye(6) * 0.35 * 0.25)
    assert np.allclose(got.w, [0.0, 0.0, 0.3])  # the body rate comes from the filtered entries it replaced
    assert h.at(190 * MS).kind == "filtered" and h.at(195 * MS).kind == "filtered"  # between a filtered and a smoothed
    assert h.at(600 * MS).kind == "filtered"
    w = h.window(480 * MS, 530 * MS)
    assert w.kind.tolist() == ["smoothed"] * 3 + ["filtered"] * 3 and w.cov.shape == (6, 6, 6)
    assert np.allclose(w.cov[0], np.eye(6) * 0.48 * 0.25)


def test_smoothed_times_need_not_match_and_never_go_back():
    h = filled(n=100)
    t, rows = smoothed_rows(h, [205, 215, 225, 233, 237, 241], 0.02)  # between the filtered times, denser
    h.add_smoothed(t, rows)
    times = h.window(190 * MS, 260 * MS).t_ns.tolist()
    assert times == [190 * MS, 200 * MS, *t.tolist(), 250 * MS, 260 * MS]  # 210..240 gone, 200 and 250 stay
    assert h.at(200 * MS).kind == "filtered" and h.at(225 * MS).kind == "smoothed"
    t2, rows2 = smoothed_rows(h, [230, 240, 250, 260], 0.03)  # overlaps what is smoothed already
    assert h.add_smoothed(t2, rows2) == 2  # only 250 and 260 are new
    assert h.at(233 * MS).p[0] == pytest.approx(0.233 + 0.02)
    assert h.at(255 * MS).kind == "smoothed" and h.at(255 * MS).p[0] == pytest.approx(0.255 + 0.03)
    times = h.window(0, 2000 * MS).t_ns
    assert np.all(np.diff(times) > 0)


def test_smoothed_history_stays_bounded_and_predictions_keep_their_kind():
    h = PoseHistory(1.0, initial_capacity=16)
    for k in range(1, 3001):  # 30 s at 100 Hz into a 1 s history, smoothed 0.3 s behind in batches
        h.add_fused(k * 10 * MS, pose_row(k * 10 * MS, h))
        if k % 25 == 0 and k > 30:
            t, rows = smoothed_rows(h, [(k - 30 - j) * 10 for j in range(24, -1, -1)], 0.0)
            h.add_smoothed(t, rows)
    h.add_predicted(30_010 * MS, pose_row(30_010 * MS, h))
    first, last = h.bounds()
    assert last - first <= 1_000_000_000 and h.capacity <= 512
    kinds = h.window(first, last).kind.tolist()
    assert kinds[0] == "smoothed" and kinds[-1] == "predicted" and "filtered" in kinds
    assert kinds == sorted(kinds, key=["smoothed", "filtered", "predicted"].index)
