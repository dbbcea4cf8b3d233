"""EuRoC import: the real MH01 folder as it is (quirks included), plus a tiny synthetic one."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import yaml

from vtolpose.drivers.files.calibration_yaml import load_yaml_file
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.estimator.core.rotation import quat_to_rot
from vtolpose.drivers.files.euroc_import import default_mounting_path, import_euroc, load_mounting, subsample

PRISM_IMU = np.array([7.48903e-02, -1.84772e-02, -1.20209e-01])  # leica0/sensor.yaml T_BS translation
R_BI = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
SIGMA = 0.02


@pytest.fixture(scope="module")
def imported(euroc_mh01: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, list[str]]:
    out = tmp_path_factory.mktemp("mh01") / "ds"
    logger = logging.getLogger("vtolpose.drivers.files.csvio")
    records: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: records.append(record.getMessage())  # type: ignore[method-assign]
    logger.addHandler(handler)
    try:
        summary = import_euroc(euroc_mh01, out, gps_rate_hz=10.0, gps_sigma_m=SIGMA, seed=0)
    finally:
        logger.removeHandler(handler)
    return out, summary, records


def seconds(ds_t: np.ndarray, t0: int) -> np.ndarray:
    return (ds_t - t0) * 1e-9


def test_junk_lines_are_skipped_counted_and_warned_once(imported) -> None:
    _, summary, records = imported
    assert summary["imu_lines_skipped"] == 7 and summary["truth_lines_skipped"] == 0
    imu_warnings = [m for m in records if "imu0/data.csv" in m]
    assert len(imu_warnings) == 1 and "skipped 7" in imu_warnings[0]
    assert summary["imu_samples"] == 36820 and summary["truth_samples"] == 3099 and summary["truth_source"] == "leica0"


def test_imu_times_exact_and_evenly_spaced(imported) -> None:
    out, _, _ = imported
    imu = Dataset.open(out).imu_raw()
    assert imu.t_ns[0] == 1403636579758560000  # "1.40363657975856E+018", exactly
    assert imu.t_ns[-1] == 1403636763853560000
    assert np.all(imu.t_ns % 10_000 == 0)  # the sci-notation copy carries 10 µs resolution
    assert np.all(np.diff(imu.t_ns) == 5_000_000)
    assert not np.any(np.isnan(imu.accel)) and not np.any(np.isnan(imu.gyro))


def test_gravity_points_down_in_body_at_rest(imported) -> None:
    out, _, _ = imported
    ds = Dataset.open(out)
    imu = ds.imu()
    s = seconds(imu.t_ns, imu.t_ns[0])
    f = imu.accel[(s > 22.0) & (s < 40.0)].mean(axis=0)
    # At rest the accelerometer reads −g in body axes: FRD down component ≈ −|g|.
    assert f[2] < -9.2
    assert np.linalg.norm(f) == pytest.approx(9.78, abs=0.1)
    tilt = np.degrees(np.arccos(-f[2] / np.linalg.norm(f)))
    assert tilt < 20.0  # the VI-sensor looks ~15° down: the body (= IMU axes) is pitched, not upside down
    np.testing.assert_array_equal(ds.calibration.imu.R_BI, R_BI)


def test_truth_is_ned_prism_track(imported, euroc_mh01: Path) -> None:
    out, summary, _ = imported
    ds = Dataset.open(out)
    truth = ds.truth()
    assert truth.q is None and truth.t_ns.size == 3099
    first = np.array([4.7822997174796811, -1.8155736277079491, 0.84462707370341705])  # tracker frame, z up
    np.testing.assert_allclose(truth.p[0], first * [1.0, -1.0, -1.0], atol=1e-9)
    s = seconds(truth.t_ns, truth.t_ns[0])
    down_at_rest = truth.p[(s > 25) & (s < 40), 2].mean()
    down_flying = truth.p[(s > 55) & (s < 75), 2].mean()
    assert down_flying < down_at_rest - 0.2  # taking off means going up: NED down decreases
    np.testing.assert_allclose(ds.calibration.truth_point_b, R_BI @ PRISM_IMU)
    np.testing.assert_allclose(summary["truth_point_b"], [-0.120209, -0.0184772, -0.0748903])
    assert ds.calibration.initial_heading_rad is None


def test_noise_is_the_in_flight_noise_of_the_setup_file(imported, tmp_path: Path, euroc_mh01: Path) -> None:
    out, _, _ = imported
    imu = Dataset.open(out).calibration.imu
    assert imu.rate_hz == 200.0
    np.testing.assert_array_equal(imu.noise.gyro_noise_density, 2.0e-3)  # in_flight_noise
    np.testing.assert_array_equal(imu.noise.accel_random_walk, 3.0e-3)
    # Without an in-flight block the datasheet figures of imu0/sensor.yaml are used.
    plain = tmp_path / "plain.yaml"
    doc = yaml.safe_load(default_mounting_path().read_text())
    del doc["in_flight_noise"]
    plain.write_text(yaml.safe_dump(doc))
    import_euroc(euroc_mh01, tmp_path / "plain", mounting=plain)
    np.testing.assert_array_equal(Dataset.open(tmp_path / "plain").calibration.imu.noise.gyro_noise_density, 1.6968e-04)


def test_gps_is_noisy_10hz_leica(imported) -> None:
    out, summary, _ = imported
    ds = Dataset.open(out)
    gps, truth = ds.gps(), ds.truth()
    assert np.median(np.diff(gps.t_ns)) == pytest.approx(1e8, rel=0.05)
    assert gps.t_ns.size == pytest.approx(10.0 * (truth.t_ns[-1] - truth.t_ns[0]) * 1e-9, rel=0.05)
    idx = np.searchsorted(truth.t_ns, gps.t_ns)
    assert np.array_equal(truth.t_ns[idx], gps.t_ns)  # fixes sit on Leica epochs
    err = gps.p_ned - truth.p[idx]
    np.testing.assert_allclose(err.std(axis=0), [SIGMA, SIGMA, np.sqrt(2) * SIGMA], rtol=0.1)
    assert np.all(gps.sigma_h == SIGMA) and np.allclose(gps.sigma_v, np.sqrt(2) * SIGMA, atol=1e-6)
    np.testing.assert_allclose(ds.calibration.gps.lever_arm_b, ds.calibration.truth_point_b)
    assert summary["gps_error_vs_truth"]["rmse_m"] == pytest.approx(2 * SIGMA, rel=0.1)


def test_same_seed_same_bytes(imported, euroc_mh01: Path, tmp_path: Path) -> None:
    out, _, _ = imported
    import_euroc(euroc_mh01, tmp_path / "again", gps_rate_hz=10.0, gps_sigma_m=SIGMA, seed=0)
    import_euroc(euroc_mh01, tmp_path / "seed1", gps_rate_hz=10.0, gps_sigma_m=SIGMA, seed=1)
    files = sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file())
    assert len(files) == 5
    for rel in files:
        assert (out / rel).read_bytes() == (tmp_path / "again" / rel).read_bytes(), rel
    gps_csv = Path("mav0/gps0/data.csv")
    assert (out / gps_csv).read_bytes() != (tmp_path / "seed1" / gps_csv).read_bytes()


# --- no shared data needed below ---------------------------------------------------------------

IMU_YAML = """T_BS: {cols: 4, rows: 4, data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}
rate_hz: 200
gyroscope_noise_density: 1.0e-04
gyroscope_random_walk: 2.0e-05
accelerometer_noise_density: 3.0e-3
accelerometer_random_walk: 4.0e-3
"""
LEICA_YAML = "T_BS: {cols: 4, rows: 4, data: [1, 0, 0, 0.1, 0, 1, 0, 0.2, 0, 0, 1, 0.3, 0, 0, 0, 1]}\n"


def tiny_euroc(root: Path) -> Path:
    (root / "mav0/imu0").mkdir(parents=True)
    (root / "mav0/leica0").mkdir(parents=True)
    (root / "mav0/imu0/sensor.yaml").write_text(IMU_YAML)
    (root / "mav0/leica0/sensor.yaml").write_text(LEICA_YAML)
    imu = ["#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
           "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"]
    imu += [f"{(1403636579758560000 + 5_000_000 * i) / 1e18:.14f}E+018,0.01,0.02,0.03,9.8,0.0,0.0" for i in range(400)]
    imu += [",,,,,,", "1403636763.853,,,,,,", "Step: 0.005 = 1/200,,,,,,"]
    leica = ["#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m]"]
    leica += [f"{1403636579758560000 + 50_000_000 * i},{0.1 * i},2.0,{1.0 + 0.01 * i}" for i in range(40)]
    (root / "mav0/imu0/data.csv").write_text("\n".join(imu) + "\n")
    (root / "mav0/leica0/data.csv").write_text("\n".join(leica) + "\n")
    return root


def test_tiny_folder_frames_and_counts(tmp_path: Path) -> None:
    summary = import_euroc(tiny_euroc(tmp_path / "src"), tmp_path / "out", gps_rate_hz=10.0, seed=3)
    assert summary["imu_lines_skipped"] == 3 and summary["imu_samples"] == 400
    ds = Dataset.open(tmp_path / "out")
    np.testing.assert_allclose(ds.imu().accel[0], [0.0, 0.0, -9.8])  # IMU x up → body down is −x
    np.testing.assert_allclose(ds.imu().gyro[0], [0.03, 0.02, -0.01])
    np.testing.assert_allclose(ds.truth().p[1], [0.1, -2.0, -1.01])
    np.testing.assert_allclose(ds.calibration.truth_point_b, [0.3, 0.2, -0.1])
    # 20 ticks of the shifted Leica track; the two before the first IMU sample are dropped.
    gps, imu_t = ds.gps(), ds.imu().t_ns
    assert gps.t_ns.size == 18 and summary["gps_fixes"] == 18
    assert imu_t[0] <= gps.t_ns[0] and gps.t_ns[-1] <= imu_t[-1]
    with pytest.raises(FileExistsError, match="already holds a dataset"):
        import_euroc(tmp_path / "src", tmp_path / "out")
    import_euroc(tmp_path / "src", tmp_path / "out", overwrite=True)
    assert Dataset.open(tmp_path / "out").gps() is None  # no stale gps0 left from the first import


def test_mounting_comes_from_the_given_file(tmp_path: Path) -> None:
    mounting = tmp_path / "identity.yaml"
    mounting.write_text("R_BI: [[1, 0, 0], [0, 1, 0], [0, 0, 1]]\nR_WL: [[1, 0, 0], [0, 1, 0], [0, 0, 1]]\n")
    import_euroc(tiny_euroc(tmp_path / "src"), tmp_path / "out", mounting=mounting)
    ds = Dataset.open(tmp_path / "out")
    np.testing.assert_allclose(ds.imu().accel[0], [9.8, 0.0, 0.0])
    np.testing.assert_allclose(ds.truth().p[1], [0.1, 2.0, 1.01])
    bad = tmp_path / "bad.yaml"
    bad.write_text("R_BI: [[1, 0, 0], [0, 1, 0], [0, 0, -1]]\nR_WL: [[1, 0, 0], [0, 1, 0], [0, 0, 1]]\n")
    with pytest.raises(ValueError, match=r"bad\.yaml: R_BI: expected a proper rotation"):
        import_euroc(tmp_path / "src", tmp_path / "out2", mounting=bad)


def test_default_mounting_file_is_the_vi_sensor() -> None:
    setup = load_mounting(default_mounting_path())
    np.testing.assert_array_equal(setup.R_BI, R_BI)
    np.testing.assert_array_equal(setup.R_WL, np.diag([1.0, -1.0, -1.0]))
    assert setup.leica_time_offset_s == pytest.approx(-0.142)
    assert setup.in_flight_noise is not None


def test_leica_stamps_are_moved_onto_the_imu_clock(imported, euroc_mh01: Path) -> None:
    out, summary, _ = imported
    truth = Dataset.open(out).truth()
    raw_first = int((euroc_mh01 / "mav0/leica0/data.csv").read_text().splitlines()[1].split(",")[0])
    assert truth.t_ns[0] == raw_first - 142_000_000
    assert summary["truth_time_offset_s"] == pytest.approx(-0.142)


def test_missing_source_files_are_named(tmp_path: Path) -> None:
    src = tiny_euroc(tmp_path / "src")
    (src / "mav0/leica0/sensor.yaml").unlink()
    with pytest.raises(FileNotFoundError, match=r"leica0/sensor\.yaml"):
        import_euroc(src, tmp_path / "out")
    (src / "mav0/imu0/sensor.yaml").write_text(IMU_YAML.replace("rate_hz: 200\n", ""))
    with pytest.raises(ValueError, match=r"imu0/sensor\.yaml: rate_hz: missing"):
        import_euroc(src, tmp_path / "out")


def test_subsample_picks_the_fix_nearest_each_tick() -> None:
    t = np.array([0, 46, 96, 150, 196, 250, 600, 650], dtype=np.int64) * 1_000_000
    assert subsample(t, 10.0).tolist() == [0, 2, 4, 6]  # ticks 0, 100, 200, 600 ms; none in the gap


# --- any EuRoC flight as it comes: truth sources, OpenCV YAML, cam0 -----------------------------

def _write_gt(root: Path, t_ns: np.ndarray, p: np.ndarray, q_wxyz: np.ndarray, folder: str, columns: int) -> None:
    (root / "mav0" / folder).mkdir(parents=True, exist_ok=True)
    rows = ["#timestamp [ns],p x,p y,p z,q w,q x,q y,q z" + ",v x,v y,v z,bw x,bw y,bw z,ba x,ba y,ba z" * (columns == 17)]
    for t, pp, q in zip(t_ns, p, q_wxyz):
        extra = [0.0] * 9 if columns == 17 else []
        rows.append(",".join([str(int(t))] + [repr(float(x)) for x in [*pp, *q, *extra]]))
    (root / "mav0" / folder / "data.csv").write_text("\n".join(rows) + "\n")


def _tiny_with_pose_truth(root: Path, folder: str, columns: int, t_bs: str) -> tuple[Path, np.ndarray]:
    src = tiny_euroc(root)
    (src / "mav0/leica0/data.csv").unlink()
    t = 1403636579758560000 + 50_000_000 * np.arange(40)
    yaw = 0.3
    q = np.tile([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)], (40, 1))  # IMU→tracker, about tracker z
    p = np.column_stack([0.1 * np.arange(40), np.full(40, 2.0), np.ones(40)])
    _write_gt(src, t, p, q, folder, columns)
    (src / "mav0" / folder / "sensor.yaml").write_text("%YAML:1.0\n" + t_bs)
    return src, p


def test_state_groundtruth_gives_pose_truth_in_our_frames(tmp_path: Path) -> None:
    src, p = _tiny_with_pose_truth(tmp_path / "src", "state_groundtruth_estimate0", 17,
                                   "T_BS: {cols: 4, rows: 4, data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}\n")
    summary = import_euroc(src, tmp_path / "out", gps_rate_hz=10.0)
    assert summary["truth_source"] == "state_groundtruth_estimate0" and summary["truth_has_attitude"]
    truth = Dataset.open(tmp_path / "out").truth()
    np.testing.assert_allclose(truth.p, p * [1.0, -1.0, -1.0], atol=1e-9)
    # Body FRD → NED: R_WL · R(q) · R_BIᵀ, with the IMU's x axis up.
    expected = np.diag([1.0, -1.0, -1.0]) @ quat_to_rot(np.array([np.cos(0.15), 0, 0, np.sin(0.15)])) @ R_BI.T
    np.testing.assert_allclose(quat_to_rot(truth.q[0]), expected, atol=1e-9)
    np.testing.assert_allclose(Dataset.open(tmp_path / "out").calibration.truth_point_b, np.zeros(3))


def test_vicon_marker_pose_is_moved_to_the_imu(tmp_path: Path) -> None:
    # The marker body sits 0.1 m along EuRoC's x from the IMU, turned 90° about z.
    src, _ = _tiny_with_pose_truth(tmp_path / "src", "vicon0", 8,
                                   "T_BS:\n  cols: 4\n  rows: 4\n  data: [0, -1, 0, 0.1, 1, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]\n")
    summary = import_euroc(src, tmp_path / "out")
    ds = Dataset.open(tmp_path / "out")
    assert summary["truth_source"] == "vicon0"
    np.testing.assert_allclose(ds.calibration.truth_point_b, R_BI @ [0.1, 0.0, 0.0])
    R_BS = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    expected = np.diag([1.0, -1.0, -1.0]) @ quat_to_rot(np.array([np.cos(0.15), 0, 0, np.sin(0.15)])) @ R_BS.T @ R_BI.T
    np.testing.assert_allclose(quat_to_rot(ds.truth().q[0]), expected, atol=1e-9)


def test_a_tum_truth_file_and_a_missing_truth(tmp_path: Path) -> None:
    src = tiny_euroc(tmp_path / "src")
    (src / "mav0/leica0/data.csv").unlink()
    with pytest.raises(ValueError, match="GPS from the truth.*has none"):
        import_euroc(src, tmp_path / "out", gps_rate_hz=10.0)
    with pytest.raises(FileNotFoundError, match="trajectory file not found"):
        import_euroc(src, tmp_path / "out", truth_file=tmp_path / "nowhere.tum")
    tum = tmp_path / "truth.tum"
    tum.write_text("# t x y z qx qy qz qw\n" + "".join(
        f"{(1403636579758560000 + 50_000_000 * i) / 1e9:.9f} {0.1 * i} 2.0 1.0 0 0 0 1\n" for i in range(40)))
    summary = import_euroc(src, tmp_path / "out", gps_rate_hz=10.0, truth_file=tum)
    assert summary["truth_source"] == "file" and summary["truth_samples"] == 40 and summary["gps_fixes"] > 0
    np.testing.assert_allclose(Dataset.open(tmp_path / "out").truth().p[1], [0.1, -2.0, -1.0])


def test_opencv_yaml_header_and_matrices_are_read(tmp_path: Path) -> None:
    path = tmp_path / "k.yaml"
    path.write_text("%YAML:1.0\n---\nK: !!opencv-matrix\n   rows: 1\n   cols: 2\n   dt: d\n   data: [ 1., 2. ]\nrate_hz: 20\n")
    assert load_yaml_file(path) == {"K": {"rows": 1, "cols": 2, "dt": "d", "data": [1.0, 2.0]}, "rate_hz": 20}


def test_v101_truth_and_camera(euroc_dev: Path, tmp_path: Path) -> None:
    src = euroc_dev / "V101"
    summary = import_euroc(src, tmp_path / "v101", gps_rate_hz=10.0, seed=1, truth_file=src / "truth.tum")
    ds = Dataset.open(tmp_path / "v101")
    assert summary["truth_has_attitude"] and summary["camera_frames"] == 95 and summary["gps_fixes"] == 1447
    # At rest the truth's attitude predicts what the accelerometer reads: gravity, to within a degree.
    truth, imu = ds.truth(), ds.imu()
    rest = imu.t_ns < truth.t_ns[0] + 4_000_000_000
    f_mean = imu.accel[rest].mean(axis=0)
    predicted = quat_to_rot(truth.q[0]).T @ np.array([0.0, 0.0, -1.0])
    assert np.degrees(np.arccos(f_mean @ predicted / np.linalg.norm(f_mean))) < 1.0
    # cam0: a forward-looking camera (its z along the body's forward axis, x right, y down).
    cam = ds.calibration.camera
    assert (cam.width, cam.height, cam.rate_hz) == (752, 480, 20.0) and cam.fx == pytest.approx(458.654)
    np.testing.assert_allclose(cam.distortion, [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0])
    np.testing.assert_allclose(cam.R_BC, [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=0.03)
    frames = ds.camera_frames()
    assert len(frames) == 95 and frames[0][0] == 1403715273262142976
    assert frames[0][1].read_bytes() == (src / "mav0/cam0/data/1403715273262142976.png").read_bytes()


CAM_YAML = """T_BS: {cols: 4, rows: 4, data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}
rate_hz: 17
resolution: [64, 36]
camera_model: pinhole
intrinsics: [45.0, 45.0, 32.0, 18.0]
distortion_model: radial-tangential
distortion_coefficients: [0.0, 0.0, 0.0, 0.0]
"""


def test_a_recording_without_truth_and_with_jpeg_frames(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A user's own recording: no truth at all, frames in JPEG (one a PNG named .jpg, one no image)."""
    import cv2

    src = tiny_euroc(tmp_path / "src")
    (src / "mav0/leica0/data.csv").unlink()
    cam = src / "mav0/cam0"
    (cam / "data").mkdir(parents=True)
    (cam / "sensor.yaml").write_text(CAM_YAML)
    image = (np.arange(64 * 36).reshape(36, 64) % 251).astype(np.uint8)
    t = [1403636579758560000 + 60_000_000 * i for i in range(4)]
    (cam / "data" / f"{t[0]}.jpg").write_bytes(cv2.imencode(".jpg", image)[1].tobytes())
    (cam / "data" / f"{t[1]}.jpg").write_bytes(cv2.imencode(".png", image)[1].tobytes())  # a PNG, whatever its name
    (cam / "data" / f"{t[2]}.jpeg").write_bytes(cv2.imencode(".jpg", image)[1].tobytes())
    (cam / "data" / f"{t[3]}.jpg").write_text("not an image")
    (cam / "data.csv").write_text("#timestamp [ns],filename\n" + "".join(
        f"{ti},{ti}{ext}\n" for ti, ext in zip(t, (".jpg", ".jpg", ".jpeg", ".jpg"))))
    with caplog.at_level(logging.WARNING):
        summary = import_euroc(src, tmp_path / "out")
    assert summary["truth_source"] == "none" and "truth_samples" not in summary
    assert summary["camera_frames"] == 3 and summary["camera_frames_skipped"] == 1
    assert any(f"{t[3]}.jpg: not a PNG or JPEG by its header" in m for m in caplog.messages)
    ds = Dataset.open(tmp_path / "out")
    assert ds.truth() is None and "no truth" in ds.meta["description"]
    frames = ds.camera_frames()
    assert [p.name for _, p in frames] == [f"{t[0]}.jpg", f"{t[1]}.png", f"{t[2]}.jpg"]
    assert frames[0][1].read_bytes() == (cam / "data" / f"{t[0]}.jpg").read_bytes()  # not re-encoded
    for _, path in frames:
        grey = ds.load_frame(path)
        assert grey is not None and grey.shape == (36, 64)


def test_the_euroc_bench_takes_only_recordings_with_a_truth(tmp_path: Path) -> None:
    """A recording of a user's own (no truth) lying beside the EuRoC flights is no bench flight."""
    from vtolpose.service.bench.euroc import find_flights

    with_leica = tiny_euroc(tmp_path / "data" / "euroc_tiny")
    without = tiny_euroc(tmp_path / "data" / "handheld")
    (without / "mav0/leica0/data.csv").unlink()
    with_tum = tiny_euroc(tmp_path / "data" / "euroc_dev" / "V9")
    (with_tum / "mav0/leica0/data.csv").unlink()
    (with_tum / "truth.tum").write_text("0 0 0 0\n")
    flights = find_flights([tmp_path / "data"])
    assert [(f.name, f.source) for f in flights] == [("TINY", with_leica), ("V9", with_tum)]
    assert flights[1].truth_file == with_tum / "truth.tum"


def test_a_kalibr_equidistant_camera_is_imported_as_a_fisheye(tmp_path: Path) -> None:
    import cv2

    src = tiny_euroc(tmp_path / "src")
    cam = src / "mav0/cam0"
    (cam / "data").mkdir(parents=True)
    (cam / "sensor.yaml").write_text(CAM_YAML.replace("radial-tangential", "equidistant")
                                     .replace("[0.0, 0.0, 0.0, 0.0]", "[0.02, -0.01, 0.003, -0.0005]"))
    t = 1403636579758560000
    (cam / "data" / f"{t}.png").write_bytes(cv2.imencode(".png", np.zeros((36, 64), np.uint8))[1].tobytes())
    (cam / "data.csv").write_text(f"#timestamp [ns],filename\n{t},{t}.png\n")
    import_euroc(src, tmp_path / "out")
    camera = Dataset.open(tmp_path / "out").calibration.camera
    assert camera.model == "equidistant"
    np.testing.assert_allclose(camera.distortion, [0.02, -0.01, 0.003, -0.0005])
