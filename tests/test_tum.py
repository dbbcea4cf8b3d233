"""TUM trajectories: exact write/read round trip, and EuRoC/Leica CSVs accepted as references."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vtolpose.drivers.files.tum import read_tum, write_tum
from vtolpose.estimator.core.rotation import quat_exp, quat_normalize


def poses(n: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1)
    t = 1403636579758560001 + 10_000_001 * np.arange(n, dtype=np.int64)
    return t, rng.normal(size=(n, 3)) * 10.0, quat_normalize(quat_exp(rng.normal(size=(n, 3))))


def test_round_trip_keeps_nanoseconds_and_quaternion_order(tmp_path: Path) -> None:
    t, p, q = poses()
    write_tum(tmp_path / "traj.txt", t, p, q)
    t2, p2, q2 = read_tum(tmp_path / "traj.txt")
    assert t2.tolist() == t.tolist()
    np.testing.assert_allclose(p2, p, atol=1e-9)
    np.testing.assert_allclose(q2, q, atol=2e-9)


def test_file_is_tum_text_x_y_z_w_order(tmp_path: Path) -> None:
    q = np.array([[np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)]])  # 90° about z, w first
    write_tum(tmp_path / "one.txt", np.array([1_500_000_001]), np.array([[1.0, 2.0, 3.0]]), q)
    lines = (tmp_path / "one.txt").read_text().splitlines()
    assert lines[0].startswith("#")
    assert lines[1] == "1.500000001 1.000000000 2.000000000 3.000000000 0.000000000 0.000000000 0.707106781 0.707106781"


def test_same_data_same_bytes(tmp_path: Path) -> None:
    t, p, q = poses()
    write_tum(tmp_path / "a.txt", t, p, q)
    write_tum(tmp_path / "b.txt", t.copy(), p.copy(), q.copy())
    assert (tmp_path / "a.txt").read_bytes() == (tmp_path / "b.txt").read_bytes()


def test_reads_euroc_ground_truth_csv(tmp_path: Path) -> None:
    f = tmp_path / "gt.csv"
    f.write_text(
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
        "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
        "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]\n"
        "1403636580838555648,4.688319,-1.786938,0.783338,0.534108,-0.153029,-0.827383,-0.082152,"
        "-0.027876,0.033207,0.800006,-0.003172,0.021267,0.078502,-0.025266,0.136696,0.075593\n"
    )
    t, p, q = read_tum(f)
    assert t.tolist() == [1403636580838555648]
    np.testing.assert_allclose(p, [[4.688319, -1.786938, 0.783338]])
    assert q[0, 0] == pytest.approx(0.534108, abs=1e-5) and q[0, 3] == pytest.approx(-0.082152, abs=1e-5)
    assert np.linalg.norm(q[0]) == pytest.approx(1.0)


def test_reads_position_only_csv(tmp_path: Path) -> None:
    f = tmp_path / "leica.csv"
    f.write_text("#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m]\n1403636578922881280,4.78,-1.81,0.84\n")
    t, p, q = read_tum(f)
    assert t.tolist() == [1403636578922881280] and q is None
    np.testing.assert_allclose(p, [[4.78, -1.81, 0.84]])


def test_tum_malformed_line_skipped(tmp_path: Path) -> None:
    f = tmp_path / "t.txt"
    f.write_text("# produced by another tool\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0\n3.0 1 1 1 0 0 0 1\n")
    t, p, q = read_tum(f)
    assert t.tolist() == [1_000_000_000, 3_000_000_000]
    np.testing.assert_allclose(q, [[1, 0, 0, 0], [1, 0, 0, 0]])


def test_non_unit_quaternion_is_an_error(tmp_path: Path) -> None:
    f = tmp_path / "t.txt"
    f.write_text("1.0 0 0 0 0 0 0 2\n")
    with pytest.raises(ValueError, match=r"t\.txt: quaternion of norm 2\.000000 at t=1\.000000000 s"):
        read_tum(f)


def test_unknown_csv_and_missing_file(tmp_path: Path) -> None:
    f = tmp_path / "odd.csv"
    f.write_text("#a,b,c\n1,2,3\n")
    with pytest.raises(ValueError, match=r"odd\.csv: CSV with 3 columns"):
        read_tum(f)
    with pytest.raises(FileNotFoundError, match="absent.txt"):
        read_tum(tmp_path / "absent.txt")
