"""Flight recorder: what it writes is what replay reads; crash-safe; a full disk stops only the recording."""

from __future__ import annotations

import errno
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from vtolpose.drivers.imu.crossbow import CrossbowScale, TimeCounter
from vtolpose.drivers.imu.crossbow_serial import CrossbowConfig, CrossbowImu
from vtolpose.drivers.files.dataset import IMU_CSV, Dataset, DatasetWriter, ImuSeries
from vtolpose.drivers.emulators import Imu400Emulator
from vtolpose.drivers.gps.common import LocalNed
from vtolpose.estimator.core.calibration import Calibration, CameraCalibration, GpsCalibration, ImuCalibration, ImuNoise
from vtolpose.estimator.core.measurements import CameraFrame
from vtolpose.estimator.core.rotation import quat_from_euler, quat_to_rot
from vtolpose.service.outputs.recorder import FlightRecorder

R_BI = quat_to_rot(quat_from_euler(0.0, np.pi, np.pi / 2))  # mounted upside down, turned


def calibration(camera: bool = False) -> Calibration:
    cam = CameraCalibration(64, 48, 50.0, 50.0, 32.0, 24.0, rate_hz=7.5) if camera else None
    return Calibration(ImuCalibration(125.0, ImuNoise.isotropic(2e-4, 2e-5, 2e-3, 3e-4), R_BI=R_BI),
                       GpsCalibration(lever_arm_b=[0.1, 0.0, -0.2]), camera=cam)


def imu_samples(n: int, seed: int = 0) -> ImuSeries:
    rng = np.random.default_rng(seed)
    return ImuSeries(5_000_000_000 + np.arange(n, dtype=np.int64) * 8_000_000,
                     rng.normal(0, 0.5, (n, 3)), rng.normal([0, 0, -9.8], 1.0, (n, 3)))


def test_recording_reads_back_as_the_same_dataset(tmp_path):
    imu = imu_samples(300)
    local = LocalNed()  # live GPS driver's frame: origin at the first fix
    fixes = [(6_000_000_000 + k * 200_000_000, 58.4 + 1e-5 * k, 15.6 - 2e-5 * k, 90.0 + 0.3 * k) for k in range(10)]
    live_ned = [local(lat, lon, alt) for _, lat, lon, alt in fixes]
    frames = [CameraFrame(5_100_000_000 + k * 133_333_333, np.full((48, 64), 10 * k, np.uint8), k) for k in range(3)]
    with FlightRecorder(tmp_path / "rec", calibration(camera=True), name="flight-1") as rec:
        for t, g, a in zip(imu.t_ns, imu.gyro, imu.accel):
            rec.record_imu(int(t), g, a)
        for (t, lat, lon, alt), k in zip(fixes, range(10)):
            rec.record_gps(t, lat, lon, alt, 0.5 + 0.01 * k, 1.1, origin=local.origin)
        for frame in frames:
            rec.record_camera(frame)
    assert rec.status == "closed" and rec.counts()["rows"] == {"imu0": 300, "gps0": 10, "cam0": 3}
    dataset = Dataset.open(tmp_path / "rec")
    assert dataset.meta["name"] == "flight-1"
    assert np.allclose(dataset.calibration.imu.R_BI, R_BI)
    assert dataset.calibration.gps.origin_lla == pytest.approx(local.origin)
    body = dataset.imu()
    assert np.array_equal(body.t_ns, imu.t_ns)
    assert np.allclose(body.gyro, imu.gyro @ R_BI.T, atol=1e-9) and np.allclose(body.accel, imu.accel @ R_BI.T, atol=1e-9)
    gps = dataset.gps()
    assert np.allclose(gps.p_ned, live_ned, atol=1e-4)  # replay converts around the same origin
    assert gps.sigma_h == pytest.approx([0.5 + 0.01 * k for k in range(10)])
    assert dataset.has_camera and dataset.skipped[IMU_CSV] == 0
    cam_lines = (tmp_path / "rec/mav0/cam0/data.csv").read_text().splitlines()
    assert cam_lines[0] == "#timestamp [ns],filename" and cam_lines[1] == f"{frames[0].t_ns},{frames[0].t_ns}.png"
    image = cv2.imread(str(tmp_path / f"rec/mav0/cam0/data/{frames[2].t_ns}.png"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(image, frames[2].image)
    # Byte for byte what the dataset writer makes of the same samples.
    DatasetWriter(tmp_path / "ref").write_imu(imu)
    assert (tmp_path / "rec" / IMU_CSV).read_bytes() == (tmp_path / "ref" / IMU_CSV).read_bytes()


def test_live_imu_from_the_emulator_records_what_the_driver_delivered(tmp_path):
    imu = imu_samples(60, seed=4)
    scale, counter = CrossbowScale(), TimeCounter(7.9e-7, True)
    with Imu400Emulator(imu.t_ns, imu.gyro, imu.accel, scale=scale, counter=counter, speed=2.0) as emu, \
            FlightRecorder(tmp_path / "live", calibration()) as rec:
        driver = CrossbowImu(CrossbowConfig(emu.port, scale=scale, counter=counter, R_BI=R_BI))
        driver.open()
        readings, start = [], time.monotonic()
        while not emu.finished.is_set() and time.monotonic() - start < 5.0:
            for r in driver.read(0.05):
                readings.append(r)
                rec.record_imu(r.t_ns, r.gyro, r.accel)
        readings += driver.read(0.05)
        driver.close()
    assert len(readings) >= 59
    replayed = Dataset.open(tmp_path / "live").imu()  # body frame, as replay feeds the estimator
    n = len(replayed.t_ns)
    assert np.array_equal(replayed.t_ns, [r.t_ns for r in readings[:n]])
    assert np.allclose(replayed.gyro, [r.sample.gyro for r in readings[:n]], atol=1e-9)
    assert np.allclose(replayed.accel, [r.sample.accel for r in readings[:n]], atol=1e-9)


def test_rows_reach_the_file_within_the_flush_interval_without_more_samples(tmp_path):
    rec = FlightRecorder(tmp_path / "r", calibration(), flush_interval_s=0.2, fsync=False)
    imu = imu_samples(10)
    for t, g, a in zip(imu.t_ns, imu.gyro, imu.accel):
        rec.record_imu(int(t), g, a)
    path = tmp_path / "r" / IMU_CSV
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline and (not path.exists() or len(path.read_text().splitlines()) < 11):
        time.sleep(0.02)
    assert len(path.read_text().splitlines()) == 11  # header + 10 rows, the recorder still open
    rec.record_imu(int(imu.t_ns[-1]), imu.gyro[0], imu.accel[0])  # not after the last: refused
    rec.record_imu(int(imu.t_ns[-1]) + 1, np.array([np.nan, 0, 0]), imu.accel[0])
    assert rec.rejected == {"out_of_order": 1, "non_finite": 1}
    rec.close()
    with pytest.raises(FileExistsError, match="already holds a recording"):
        FlightRecorder(tmp_path / "r", calibration())


def test_sigkill_loses_at_most_the_last_second(tmp_path):
    root = tmp_path / "killed"
    script = textwrap.dedent(f"""
        import time, numpy as np
        from vtolpose.estimator.core.calibration import Calibration, ImuCalibration, ImuNoise
        from vtolpose.service.outputs.recorder import FlightRecorder
        rec = FlightRecorder({str(root)!r}, Calibration(ImuCalibration(250.0, ImuNoise.isotropic(1e-4, 1e-5, 1e-3, 1e-4))),
                             flush_interval_s=1.0)
        print("ready", flush=True)
        while True:
            rec.record_imu(time.monotonic_ns(), np.zeros(3), np.array([0.0, 0.0, -9.81]))
            time.sleep(0.004)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    imu_file, deadline = root / IMU_CSV, time.monotonic() + 30.0
    while time.monotonic() < deadline and (not imu_file.exists() or imu_file.read_bytes().count(b"\n") <= 101):
        time.sleep(0.02)  # until a flush wrote more than 100 rows (a loaded machine runs the writer slowly)
    assert imu_file.exists() and imu_file.read_bytes().count(b"\n") > 101, "no rows reached the file in 30 s"
    time.sleep(1.6)  # a flush has just written them: the next one comes 1 s later, then kill 0.6 s after it
    killed_at = time.monotonic_ns()
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=5)
    data = Dataset.open(root).imu_raw()  # a torn last line would be skipped and counted, not fatal
    assert len(data.t_ns) > 100
    assert killed_at - data.t_ns[-1] <= 1.0e9 + 0.15e9, "more than the last second was lost"


class FullDisk:
    """A file that accepts ``room`` bytes, then fails like a full disk."""

    def __init__(self, path: Path, mode: str, room: list[int], **kwargs) -> None:
        self._file, self._room = open(path, mode, **kwargs), room

    def write(self, data):
        size = len(data.encode() if isinstance(data, str) else data)
        if size > self._room[0]:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self._file.name))
        self._room[0] -= size
        return self._file.write(data)

    def __getattr__(self, name):
        return getattr(self._file, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._file.close()


def test_full_disk_stops_recording_loudly_but_never_raises(tmp_path, caplog):
    room, statuses = [20_000], []
    rec = FlightRecorder(tmp_path / "full", calibration(), flush_interval_s=60.0, fsync=False,
                         opener=lambda path, mode, **kw: FullDisk(path, mode, room, **kw), on_status=statuses.append)
    imu = imu_samples(400)
    with caplog.at_level(logging.ERROR, logger="vtolpose.service.outputs.recorder"):
        for k, (t, g, a) in enumerate(zip(imu.t_ns, imu.gyro, imu.accel)):
            rec.record_imu(int(t), g, a)  # the estimator's thread: must never see an exception
            if k % 50 == 49:
                rec.flush()  # what the background flusher does every second
        rec.record_camera(CameraFrame(int(imu.t_ns[-1]), np.zeros((4, 4), np.uint8)))
        rec.flush()
        rec.close()
    assert rec.status.startswith("stopped:") and "No space left on device" in rec.status
    assert statuses == [rec.status]  # announced once
    assert rec.dropped > 0 and rec.ok is False
    assert any("RECORDING STOPPED" in r.message for r in caplog.records)
    data = Dataset.open(tmp_path / "full").imu_raw()  # what made it to disk is still a valid dataset
    assert 0 < len(data.t_ns) < 400 and len(data.t_ns) % 50 == 0  # whole batches, no torn line


def test_record_dir_start_placeholder_gives_each_start_its_own_folder():
    import datetime

    from vtolpose.service.commands.run import recording_folder

    start = datetime.datetime(2026, 11, 22, 10, 31, 5, tzinfo=datetime.timezone.utc)
    assert recording_folder("/data/flights/{start}", start) == "/data/flights/20261122T103105Z"
    assert recording_folder("/data/flight-7", start) == "/data/flight-7"
