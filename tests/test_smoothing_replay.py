"""``vtolpose replay --smooth``: the files it writes, the side-by-side report, a flight recording as input,
and a forward record that cannot be written."""

from __future__ import annotations

import json

import numpy as np
import pymap3d
import pytest

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.files.tum import read_tum
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.service.cli import main
from vtolpose.service.outputs.recorder import FlightRecorder
from vtolpose.service.replay import smoothing as smoothing_module
from vtolpose.service.replay.smoothing import StepFiles, replay_smoothed


@pytest.fixture(scope="module")
def flight():
    return simulate_flight("landfill", 40.0, 2)


@pytest.fixture(scope="module")
def flight_dir(flight, tmp_path_factory):
    return write_flight(flight, tmp_path_factory.mktemp("smooth-replay") / "landfill")


def test_replay_smooth_writes_the_smoothed_trajectory_its_covariances_and_the_report(flight_dir, tmp_path):
    out, cov, filtered, report = (tmp_path / name for name in ("s.txt", "s_cov.csv", "f.txt", "r.json"))
    code = main(["replay", str(flight_dir), "--smooth", "--out", str(out), "--cov", str(cov), "--filtered-out",
                 str(filtered), "--report", str(report), "--score-from", "15", "--no-progress",
                 "--set", "smoothing.chunk_steps=500"])  # several chunks on disk
    assert code == 0
    t_s, p_s, q_s = read_tum(out)
    t_f, _, _ = read_tum(filtered)
    assert np.all(np.diff(t_s) > 0) and abs(int(t_s[-1]) - int(t_f[-1])) < 20_000_000
    lines = cov.read_text().splitlines()
    assert lines[0].startswith("#") and len(lines) == len(t_s) + 1
    values = np.array([[float(v) for v in line.split(",")] for line in lines[1:]])
    assert values.shape[1] == 22 and np.allclose(values[:, 0] * 1e9, t_s, atol=1.0)
    full = np.zeros((len(values), 6, 6))
    full[:, *np.triu_indices(6)] = values[:, 1:]
    full = full + np.swapaxes(np.triu(full, 1), 1, 2)
    assert np.all(np.linalg.eigvalsh(full) > 0)  # each a covariance
    doc = json.loads(report.read_text())
    sm = doc["smoothing"]
    assert doc["score_from_s"] == 15.0 and set(sm) >= {"filtered", "smoothed", "fixed_lag", "backward_s"}
    assert sm["smoothed"]["position_rmse_m"] < 0.7 * sm["filtered"]["position_rmse_m"]
    assert sm["fixed_lag"]["position_rmse_m"] < sm["filtered"]["position_rmse_m"]
    assert sm["filtered"]["position_rmse_m"] == doc["position_rmse_m"]
    lo, hi = sm["smoothed"]["nees"]["band_per_sample"]
    assert lo < sm["smoothed"]["nees_mean"] < hi
    assert sm["segments"] == 1 and sm["steps"] > 1000 and sm["disk_mb"] > 0


def test_filtered_out_and_cov_need_smooth(flight_dir, tmp_path, capsys):
    assert main(["replay", str(flight_dir), "--cov", str(tmp_path / "c.csv"), "--no-progress"]) != 0
    assert "--cov come with --smooth" in capsys.readouterr().err


def test_a_flight_recording_smooths_as_the_flight_it_recorded(flight, flight_dir, tmp_path):
    """What `vtolpose run --record` writes (sensor-axis IMU, WGS84 GPS, the live origin), replayed with --smooth."""
    cal = Dataset.open(flight_dir).calibration
    origin = cal.gps.origin_lla
    rec_dir = tmp_path / "rec"
    with FlightRecorder(rec_dir, cal, name="recorded") as rec:
        R_IB = cal.imu.R_BI.T
        for t, g, a in zip(flight.imu.t_ns, flight.imu.gyro, flight.imu.accel):
            rec.record_imu(int(t), R_IB @ g, R_IB @ a)
        for t, p, h, v in zip(flight.gps.t_ns, flight.gps.p_ned, flight.gps.sigma_h, flight.gps.sigma_v):
            lat, lon, alt = pymap3d.ned2geodetic(*p, *origin)
            rec.record_gps(int(t), lat, lon, alt, float(h), float(v), origin=origin)
    cfg = load_config()
    recorded = replay_smoothed(Dataset.open(rec_dir), cfg, sensors=["imu", "gps"]).smoothing.smoothed
    original = replay_smoothed(Dataset.open(flight_dir), cfg, sensors=["imu", "gps"]).smoothing.smoothed
    assert len(recorded.t_ns) > 1000 and np.array_equal(recorded.t_ns, original.t_ns)
    assert np.max(np.abs(recorded.p - original.p)) < 1e-4  # WGS84 text and back: sub-millimetre


def test_a_forward_record_that_cannot_be_written_stops_the_smoothing_not_the_filter(monkeypatch, tmp_path):
    files = StepFiles(chunk_steps=16, folder=str(tmp_path))

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(smoothing_module.np, "save", full_disk)
    from vtolpose.estimator.smoothing.steps import Step

    for k in range(40):  # two chunks' worth: the first write fails, the rest are dropped quietly
        files.add(Step(0, k, np.zeros(16), np.eye(15), k + 1, np.eye(15), np.zeros(16), np.eye(15)))
    with pytest.raises(OSError, match="could not be written.*smoothing.temp_dir"):
        next(files.newest_first())
    files.close()


def test_an_unusable_temp_dir_is_named(tmp_path):
    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("x")
    with pytest.raises(OSError, match="smoothing.temp_dir.*file"):
        StepFiles(16, str(not_a_folder))
