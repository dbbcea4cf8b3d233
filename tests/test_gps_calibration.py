"""GPS time offset and lever arm from the in-motion alignment model, with known answers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset, DatasetWriter
from vtolpose.drivers.files.euroc_import import default_mounting_path, import_euroc
from vtolpose.drivers.files.series import GpsSeries
from vtolpose.drivers.simulator import GpsErrorModel, ImuErrorModel, SimulationOptions
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.drivers.simulator.gps_model import antenna_positions
from vtolpose.drivers.simulator.imu_model import corrupt_imu
from vtolpose.drivers.simulator.trajectory import EulerTrajectory, SineMotion
from vtolpose.estimator.calibration.gps import GpsCalibOptions, GpsCalibrationError, fit_lever_arm, scan_latency
from vtolpose.service.calibration.plots import plot_latency
from vtolpose.service.cli import main

G = 9.80665
LATENCY_S = 0.08  # the fixes are stamped this late: the offset to find is -LATENCY_S
FAST = GpsCalibOptions(windows=5, max_offset_s=0.16, step_s=0.02, sigma_gyro_bias=0.005)  # a light scan


def sigmas(gps: GpsSeries) -> np.ndarray:
    return np.column_stack([gps.sigma_h, gps.sigma_h, gps.sigma_v])


@pytest.fixture(scope="module")
def book(simulated_flight):
    lever = (0.1, -0.05, -0.2)
    return simulated_flight("book", 60.0, 3, SimulationOptions(gps=GpsErrorModel(0.02, lever_arm_b=lever)))


def rest_bias(flight) -> np.ndarray:
    """The gyro bias as a still start measures it (the prior the CLI gives the fit)."""
    still = flight.imu.t_ns < flight.imu.t_ns[0] + int(9e9)
    return flight.imu.gyro[still].mean(axis=0)


def test_latency_of_a_simulated_gps_is_found(book, tmp_path) -> None:
    imu, gps = book.imu, book.gps
    late = gps.t_ns + int(LATENCY_S * 1e9)
    scan = scan_latency(imu.t_ns, imu.gyro, imu.accel, late, gps.p_ned, sigmas(gps), G,
                        book.calibration.gps.lever_arm_b, FAST, gyro_bias_prior=rest_bias(book))
    # Measured with this light scan: -82.7 ms ± 2.9 ms (the CLI default, 7 windows by 10 ms: -81.1 ± 2.8).
    assert scan.offset_s == pytest.approx(-LATENCY_S, abs=0.005)
    assert 0.0 < scan.sigma_s < 0.006
    assert abs(scan.offset_s + LATENCY_S) < 3.0 * scan.sigma_s
    assert scan.residual_ratio == pytest.approx(1.0, abs=0.15)  # the model fits to the GPS noise
    assert scan.cost[0] > 1.3 * scan.cost.min() and scan.cost[-1] > 4.0 * scan.cost.min()  # a clear valley
    assert plot_latency(tmp_path / "latency.png", scan).read_bytes().startswith(b"\x89PNG")


def waving(duration_s: float, seed: int):
    """A calibration manoeuvre as the error message asks for: tilts of ±20°, yaw swings of ±70°."""
    rng = np.random.default_rng(seed)
    freq = np.array([[0.9, 1.7], [1.1, 2.1], [0.5, 1.3]])
    position = SineMotion(np.array([0.0, 0.0, -1.0]), np.array([[0.3, 0.1], [0.3, 0.1], [0.15, 0.05]]),
                          freq * 1.3, rng.uniform(0, 6, (3, 2)), 5.0, 2.0)
    attitude = SineMotion(np.zeros(3), np.array([[0.3, 0.08], [0.3, 0.08], [1.1, 0.15]]), freq,
                          rng.uniform(0, 6, (3, 2)), 5.0, 2.0)
    trajectory = EulerTrajectory(position, attitude)
    model = ImuErrorModel()
    t_imu = np.arange(0.0, duration_s, 1.0 / model.rate_hz)
    k = trajectory.kinematics(t_imu)
    imu = corrupt_imu(k.omega_b(), k.specific_force_b(G), model, rng)
    t_gps = np.arange(0.0, duration_s, 0.1)
    kg = trajectory.kinematics(t_gps)
    lever = GpsErrorModel(0.02, lever_arm_b=(0.25, -0.1, -0.3))
    p = antenna_positions(kg.p, kg.rotation(), lever) + rng.standard_normal((len(t_gps), 3)) * lever.sigmas
    ns = lambda t: (1e9 + np.round(t * 1e9)).astype(np.int64)  # noqa: E731
    return ns(t_imu), imu, ns(t_gps), p, np.asarray(lever.lever_arm_b), imu.gyro[: 5 * 125].mean(axis=0)


def test_lever_arm_of_a_waved_antenna_is_found() -> None:
    t_imu, imu, t_gps, p, lever, bias = waving(50.0, seed=2)
    fit = fit_lever_arm(t_imu, imu.gyro, imu.accel, t_gps, p, np.array([0.02, 0.02, 0.028]), G,
                        options=FAST, gyro_bias_prior=bias)
    assert np.all(fit.sigma_m < 0.02)  # measured ±[1.5, 1.6, 1.2] cm, off by [+0.9, -0.8, +1.2] cm
    np.testing.assert_allclose(fit.lever_arm_b, lever, atol=max(0.02, 3.0 * float(np.max(fit.sigma_m))))
    assert np.linalg.norm(fit.lever_arm_b - lever) < 0.03


def test_too_little_motion_is_an_error_that_says_what_to_record(book) -> None:
    imu, gps = book.imu, book.gps
    rest_imu = imu.t_ns < imu.t_ns[0] + int(9.5e9)
    rest_gps = gps.t_ns < gps.t_ns[0] + int(9.5e9)
    with pytest.raises(GpsCalibrationError, match=r"too little motion.*record the vehicle moving"):
        scan_latency(imu.t_ns[rest_imu], imu.gyro[rest_imu], imu.accel[rest_imu], gps.t_ns[rest_gps],
                     gps.p_ned[rest_gps], sigmas(gps)[rest_gps], G, np.zeros(3), dataclasses.replace(FAST, window_s=3.0))


def test_lever_arm_without_rotation_is_refused() -> None:
    """Pure translation: the antenna never swings around the IMU, so its offset cannot show."""
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 40.0, 1.0 / 125.0)
    t_gps = np.arange(0.0, 40.0, 0.1)
    accel = np.column_stack([0.8 * np.sin(1.3 * t), 0.6 * np.cos(0.9 * t), np.full(len(t), -G)])
    accel += rng.standard_normal((len(t), 3)) * 2e-3 * np.sqrt(125.0)
    gyro = rng.standard_normal((len(t), 3)) * 3e-4 * np.sqrt(125.0)
    p = np.column_stack([-0.8 / 1.3**2 * np.sin(1.3 * t_gps), -0.6 / 0.9**2 * np.cos(0.9 * t_gps), np.zeros_like(t_gps)])
    p += np.array([0.25, -0.1, -0.3]) + rng.standard_normal((len(t_gps), 3)) * 0.02
    ns = lambda s: (1e9 + np.round(s * 1e9)).astype(np.int64)  # noqa: E731
    with pytest.raises(GpsCalibrationError, match=r"lever arm is not determined.*record turns"):
        fit_lever_arm(ns(t), gyro, accel, ns(t_gps), p, np.array([0.02, 0.02, 0.028]), G, options=FAST)


def test_cli_writes_offset_and_lever_arm_blocks(book, tmp_path, capsys) -> None:
    root = write_flight(book, tmp_path / "book")
    late = dataclasses.replace(book.gps, t_ns=book.gps.t_ns + int(LATENCY_S * 1e9))
    DatasetWriter(root).write_gps(late)
    out = tmp_path / "gps.yaml"
    assert main(["calibrate", "gps-latency", str(root), "--max-offset", "0.16", "--step", "0.02", "--windows", "4",
                 "--out", str(out), "--no-plot"]) == 0
    assert load_config(out)["calibration.gps.time_offset_s"] == pytest.approx(-LATENCY_S, abs=0.005)
    assert "gyro bias prior: from the rest stretch" in capsys.readouterr().out
    # The book arm tilts by ±8° only: the lever arm shows to ±5 cm, which is refused, not written.
    lever_out = tmp_path / "lever.yaml"
    assert main(["calibrate", "lever-arm", str(root), "--offset", "-0.08", "--windows", "4", "--out", str(lever_out)]) == 1
    assert "lever arm is not determined" in capsys.readouterr().err
    assert not lever_out.exists()


def mh01_scan(src, out, mounting=None, centre_s: float = 0.0):
    import_euroc(src, out, gps_rate_hz=10.0, gps_sigma_m=0.02, mounting=mounting)
    ds = Dataset.open(out)
    imu, gps = ds.imu(), ds.gps()
    still = (imu.t_ns > imu.t_ns[0] + int(23e9)) & (imu.t_ns < imu.t_ns[0] + int(40e9))
    options = dataclasses.replace(FAST, centre_s=centre_s, max_offset_s=0.06, step_s=0.02, windows=4)
    return scan_latency(imu.t_ns, imu.gyro, imu.accel, gps.t_ns, gps.p_ned, sigmas(gps), ds.calibration.imu.gravity,
                        ds.calibration.gps.lever_arm_b, options, gyro_bias_prior=imu.gyro[still].mean(axis=0))


def test_euroc_mh01_leica_clock_offset(euroc_mh01, tmp_path) -> None:
    """The importer moves the Leica stamps by the configured -142 ms; imported as they are, the
    scan finds that offset, and after the importer's shift only a small remainder."""
    raw = tmp_path / "raw_mounting.yaml"
    mounting = yaml.safe_load(default_mounting_path().read_text())
    raw.write_text(yaml.safe_dump({**mounting, "leica_time_offset_s": 0.0}))
    # Measured with the CLI defaults (7 windows, ±300 ms by 10 ms): -137.4 ± 4.9 ms raw (GPS).
    assert -0.165 < mh01_scan(euroc_mh01, tmp_path / "raw", raw, centre_s=-0.15).offset_s < -0.115
    assert abs(mh01_scan(euroc_mh01, tmp_path / "mh01").offset_s) < 0.03
