"""Dataset folders: write → read round trips, frames on read, determinism, and bad input."""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from vtolpose.drivers.files.dataset import (
    CalibrationError,
    Dataset,
    DatasetWriter,
    GpsSeries,
    ImuSeries,
    TruthSeries,
    calibration_from_yaml,
    calibration_to_yaml,
)
from vtolpose.estimator.core.calibration import Calibration, CameraCalibration, GpsCalibration, ImuCalibration, ImuNoise
from vtolpose.estimator.core.rotation import quat_exp, quat_normalize

R_BI = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
ORIGIN = (58.4, 15.6, 60.0)


def calibration(origin=ORIGIN, camera: bool = True) -> Calibration:
    return Calibration(
        imu=ImuCalibration(
            rate_hz=125.0,
            noise=ImuNoise(np.array([3e-4, 3e-4, 4e-4]), 2e-5, 2e-3, 3e-4),
            R_BI=R_BI,
            gravity=9.81,
        ),
        gps=GpsCalibration(lever_arm_b=[0.1, -0.2, -0.3], origin_lla=origin),
        camera=CameraCalibration(656, 494, 500.0, 501.0, 328.0, 247.0, [0.1, -0.2, 0.001, 0.002, 0.0],
                                 R_BI.T, [0.05, 0.0, 0.1], 7.5, 0.004) if camera else None,
        initial_heading_rad=math.radians(30.0),
        truth_point_b=[0.0, 0.0, 0.1],
    )


def series(n: int = 50):
    rng = np.random.default_rng(3)
    t = 1_000_000_000 + 8_000_000 * np.arange(n, dtype=np.int64)
    imu = ImuSeries(t, rng.normal(size=(n, 3)) * 0.1, rng.normal(size=(n, 3)) + [9.8, 0, 0])
    gps = GpsSeries(t[::5], rng.normal(size=(n // 5, 3)) * 50.0, 1.5, 3.0)
    q = quat_normalize(quat_exp(rng.normal(size=(n, 3))))
    truth = TruthSeries(t, rng.normal(size=(n, 3)), q, rng.normal(size=(n, 3)))
    return imu, gps, truth


def write_dataset(root: Path, geodetic: bool = True) -> tuple[ImuSeries, GpsSeries, TruthSeries]:
    imu, gps, truth = series()
    w = DatasetWriter(root)
    w.write_calibration(calibration(), "unit", "written by test_dataset")
    w.write_imu(imu)
    w.write_gps(gps, ORIGIN if geodetic else None)
    w.write_truth(truth, biases_g=np.full(3, 1e-3))
    return imu, gps, truth


def test_calibration_yaml_round_trip() -> None:
    cal = calibration()
    back = calibration_from_yaml(yaml.safe_load(yaml.safe_dump(calibration_to_yaml(cal))))
    np.testing.assert_array_equal(back.imu.R_BI, cal.imu.R_BI)
    np.testing.assert_array_equal(back.imu.noise.gyro_noise_density, [3e-4, 3e-4, 4e-4])
    np.testing.assert_array_equal(back.imu.noise.accel_random_walk, [3e-4] * 3)
    assert back.imu.rate_hz == 125.0 and back.imu.gravity == 9.81
    assert back.gps.origin_lla == ORIGIN
    np.testing.assert_array_equal(back.gps.lever_arm_b, [0.1, -0.2, -0.3])
    assert back.initial_heading_rad == pytest.approx(math.radians(30.0))
    np.testing.assert_array_equal(back.truth_point_b, [0.0, 0.0, 0.1])
    assert back.camera.width == 656 and back.camera.fy == 501.0 and back.camera.time_offset_s == 0.004
    np.testing.assert_array_equal(back.camera.distortion, [0.1, -0.2, 0.001, 0.002, 0.0])
    np.testing.assert_array_equal(back.camera.R_BC, R_BI.T)


def test_minimal_yaml_takes_documented_defaults() -> None:
    cal = calibration_from_yaml({"imu": {"rate_hz": 200, "noise": {
        "gyro_noise_density": 1e-4, "gyro_random_walk": 1e-5, "accel_noise_density": 1e-3, "accel_random_walk": 1e-4}}})
    np.testing.assert_array_equal(cal.imu.R_BI, np.eye(3))
    assert cal.gps.origin_lla is None and cal.camera is None and cal.initial_heading_rad is None


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d["imu"]["noise"].update(gyro_noise_density="abc"),
         "dataset.yaml: imu.noise.gyro_noise_density: expected a number or a list of 3 numbers, got 'abc'"),
        (lambda d: d["imu"]["noise"].update(gyro_random_walk=[1, 2]),
         "imu.noise.gyro_random_walk: expected a number or a list of 3"),
        (lambda d: d["imu"]["noise"].update(accel_noise_density=-1.0), "imu.noise.accel_noise_density: expected"),
        (lambda d: d["imu"].pop("rate_hz"), "imu.rate_hz: missing"),
        (lambda d: d["imu"].update(rate_hz=True), "imu.rate_hz: expected a finite number, got True"),
        (lambda d: d["imu"].update(R_BI=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]), "imu.R_BI: expected a proper rotation"),
        (lambda d: d["gps"].update(leverarm_b=[0, 0, 0]), "gps: unknown key(s) ['leverarm_b']"),
        (lambda d: d["gps"].update(origin={"lat": 95.0, "lon": 0.0, "alt": 0.0}), "gps.origin: expected lat in"),
        (lambda d: d["init"].update(heading_deg="north"), "init.heading_deg: expected a finite number"),
        (lambda d: d["camera"].update(width=656.5), "camera.width: expected a positive integer, got 656.5"),
        (lambda d: d["camera"].update(distortion=[0, 0, 0, 0]), "camera.distortion: expected a list of 5 numbers"),
        (lambda d: d["truth"].update(point_b="0 0 0"), "truth.point_b: expected a list of 3 numbers"),
    ],
)
def test_bad_yaml_values_name_the_key(edit, message: str) -> None:
    doc = calibration_to_yaml(calibration())
    edit(doc)
    with pytest.raises(CalibrationError, match=re.escape(message)):
        calibration_from_yaml(doc)


def test_write_read_round_trip_geodetic(tmp_path: Path) -> None:
    imu, gps, truth = write_dataset(tmp_path / "ds")
    ds = Dataset.open(tmp_path / "ds")
    assert ds.meta == {"name": "unit", "description": "written by test_dataset"}
    raw = ds.imu_raw()
    assert raw.t_ns.tolist() == imu.t_ns.tolist()
    np.testing.assert_allclose(raw.accel, imu.accel, atol=1e-10)
    body = ds.imu()
    np.testing.assert_allclose(body.accel, imu.accel @ R_BI.T, atol=1e-10)
    np.testing.assert_allclose(body.gyro, imu.gyro @ R_BI.T, atol=1e-10)
    np.testing.assert_allclose(ds.imu(np.eye(3)).gyro, imu.gyro, atol=1e-10)
    g = ds.gps()
    assert g.t_ns.tolist() == gps.t_ns.tolist() and g.origin_lla == ORIGIN
    np.testing.assert_allclose(g.p_ned, gps.p_ned, atol=2e-5)  # 1e-10 deg ≈ 1e-5 m
    np.testing.assert_allclose(g.sigma_h, 1.5) and np.testing.assert_allclose(g.sigma_v, 3.0)
    tr = ds.truth()
    np.testing.assert_allclose(tr.p, truth.p, atol=1e-9)
    np.testing.assert_allclose(tr.q, truth.q, atol=1e-11)
    np.testing.assert_allclose(tr.v, truth.v, atol=1e-9)
    np.testing.assert_allclose(tr.bias_g, 1e-3) and np.testing.assert_allclose(tr.bias_a, 0.0)
    assert ds.skipped == {"mav0/imu0/data.csv": 0, "mav0/gps0/data.csv": 0,
                          "mav0/state_groundtruth_estimate0/data.csv": 0}
    assert yaml.safe_load((tmp_path / "ds/mav0/gps0/sensor.yaml").read_text())["frame"] == "WGS84"


def test_local_ned_gps_and_first_fix_origin(tmp_path: Path) -> None:
    _, gps, _ = write_dataset(tmp_path / "ned", geodetic=False)
    np.testing.assert_allclose(Dataset.open(tmp_path / "ned").gps().p_ned, gps.p_ned, atol=1e-6)
    # Geodetic fixes with a null origin: local NED around the first fix.
    w = DatasetWriter(tmp_path / "first")
    w.write_calibration(calibration(origin=None), "first", "")
    w.write_gps(gps, ORIGIN)
    g = Dataset.open(tmp_path / "first").gps()
    # Tangent planes ~100 m apart differ by a few mm over these ~100 m offsets.
    np.testing.assert_allclose(g.p_ned, gps.p_ned - gps.p_ned[0], atol=5e-3)
    np.testing.assert_allclose(g.p_ned[0], 0.0, atol=1e-6)
    assert g.origin_lla[0] != ORIGIN[0]


def test_same_data_same_bytes(tmp_path: Path) -> None:
    write_dataset(tmp_path / "a")
    write_dataset(tmp_path / "b")
    files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    assert len(files) == 5
    for rel in files:
        assert (tmp_path / "a" / rel).read_bytes() == (tmp_path / "b" / rel).read_bytes(), rel


def test_truth_prefers_full_then_leica_then_none(tmp_path: Path) -> None:
    _, _, truth = series()
    w = DatasetWriter(tmp_path / "d")
    w.write_calibration(calibration(camera=False), "d", "")
    assert Dataset.open(tmp_path / "d").truth() is None
    assert Dataset.open(tmp_path / "d").gps() is None
    w.write_truth(TruthSeries(truth.t_ns, truth.p))
    leica = Dataset.open(tmp_path / "d").truth()
    assert leica.q is None and leica.v is None
    np.testing.assert_allclose(leica.p, truth.p, atol=1e-9)
    w.write_truth(truth)
    assert Dataset.open(tmp_path / "d").truth().q is not None


def test_full_truth_needs_velocity(tmp_path: Path) -> None:
    _, _, truth = series()
    with pytest.raises(ValueError, match="needs v"):
        DatasetWriter(tmp_path).write_truth(TruthSeries(truth.t_ns, truth.p, truth.q))


def test_bad_imu_lines_are_counted(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    imu, _, _ = write_dataset(tmp_path / "ds")
    path = tmp_path / "ds/mav0/imu0/data.csv"
    path.write_text(path.read_text() + "99999999999,1,2,3,nan,5,6\n,,,,,,\n")
    with caplog.at_level(logging.WARNING):
        ds = Dataset.open(tmp_path / "ds")
        assert ds.imu().t_ns.size == imu.t_ns.size
    assert ds.skipped["mav0/imu0/data.csv"] == 2
    assert sum("skipped 2" in r.getMessage() for r in caplog.records) == 1


def test_gps_fix_with_non_positive_sigma_is_counted(tmp_path: Path) -> None:
    _, gps, _ = write_dataset(tmp_path / "ds", geodetic=False)
    path = tmp_path / "ds/mav0/gps0/data.csv"
    path.write_text(path.read_text() + "9999999999,1,2,3,0.0,1.0\n")
    ds = Dataset.open(tmp_path / "ds")
    assert ds.gps().t_ns.size == gps.t_ns.size
    assert ds.skipped["mav0/gps0/data.csv"] == 1


def test_missing_column_in_imu_header_is_an_error(tmp_path: Path) -> None:
    write_dataset(tmp_path / "ds")
    path = tmp_path / "ds/mav0/imu0/data.csv"
    lines = path.read_text().splitlines()
    path.write_text("\n".join([lines[0].rsplit(",", 1)[0], *lines[1:]]) + "\n")
    with pytest.raises(ValueError, match=r"imu0/data\.csv: header line 1 has 6 columns, expected 7"):
        Dataset.open(tmp_path / "ds").imu()


def test_open_errors_name_the_problem(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nowhere"):
        Dataset.open(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match=r"empty/dataset\.yaml"):
        Dataset.open(tmp_path / "empty")
    write_dataset(tmp_path / "ds")
    path = tmp_path / "ds/dataset.yaml"
    path.write_text(path.read_text().replace("vtolpose-dataset/1", "vtolpose-dataset/9"))
    with pytest.raises(CalibrationError, match="format: expected 'vtolpose-dataset/1', got 'vtolpose-dataset/9'"):
        Dataset.open(tmp_path / "ds")
    write_dataset(tmp_path / "ds2")
    (tmp_path / "ds2/mav0/gps0/sensor.yaml").unlink()
    with pytest.raises(FileNotFoundError, match=r"gps0/sensor\.yaml"):
        Dataset.open(tmp_path / "ds2").gps()
    with pytest.raises(FileNotFoundError, match=r"imu0/data\.csv: file not found"):
        Dataset.open(_no_imu(tmp_path)).imu()


def _no_imu(tmp_path: Path) -> Path:
    root = tmp_path / "noimu"
    DatasetWriter(root).write_calibration(calibration(), "x", "")
    return root


def test_has_camera_needs_images_and_calibration(tmp_path: Path) -> None:
    write_dataset(tmp_path / "ds")
    assert not Dataset.open(tmp_path / "ds").has_camera
    (tmp_path / "ds/mav0/cam0").mkdir(parents=True)
    (tmp_path / "ds/mav0/cam0/data.csv").write_text("#timestamp [ns],filename\n")
    assert Dataset.open(tmp_path / "ds").has_camera


def test_series_shapes_are_checked() -> None:
    with pytest.raises(ValueError, match=r"ImuSeries.accel: expected shape \(2, 3\)"):
        ImuSeries(np.array([1, 2]), np.zeros((2, 3)), np.zeros((3, 3)))
