"""``vtolpose probe``: the field check, run through the real CLI against the device emulators."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest

from vtolpose.drivers.emulators import Imu400Emulator, NmeaEmulator, NmeaEpoch
from vtolpose.service.cli import main


def test_probe_imu_prints_identity_rate_samples_and_statistics(capsys):
    n = 100
    t = np.arange(n, dtype=np.int64) * 8_000_000
    gyro = np.column_stack([np.linspace(-0.5, 0.5, n), np.zeros(n), np.full(n, 0.1)])
    accel = np.tile([0.0, 0.0, -9.80665], (n, 1))
    with Imu400Emulator(t, gyro, accel, serial_number=4242) as emu:
        code = main(["probe", "imu", "--port", emu.port, "--seconds", "0.6", "--samples", "3"])
    out = capsys.readouterr().out.splitlines()
    assert code == 0
    assert any(line == "identity: version 'IMU400CC-100 emulated', serial number 4242 (0x00001092)" for line in out)
    header = out.index(next(line for line in out if line.startswith("t [s],gyro_x")))
    rows = [line.split(",") for line in out[header + 1:header + 4]]
    assert [float(r[0]) for r in rows][0] == 0.0 and all(len(r) == 9 for r in rows)
    assert [float(r[6]) for r in rows] == [-9.806650] * 3 or all(abs(float(r[6]) + 9.80665) < 1e-3 for r in rows)
    rate = re.fullmatch(r"rate: ([\d.]+) Hz over [\d.]+ s \((\d+) samples\) \(nominal 125 Hz\)",
                        next(line for line in out if line.startswith("rate:")))
    n_got = int(rate[2])
    sent = [p.sent_ns for p in emu.sent[:n_got]]
    assert float(rate[1]) == pytest.approx((n_got - 1) / ((sent[-1] - sent[0]) * 1e-9), rel=0.1)
    assert any(line.startswith("packets: good ") and ", bad 0," in line for line in out)
    assert any("consistent with the configuration" in line for line in out)


def test_probe_imu_flags_a_wrong_counter_direction(capsys):
    n = 60
    with Imu400Emulator(np.arange(n, dtype=np.int64) * 8_000_000, np.zeros((n, 3)), np.zeros((n, 3))) as emu:
        code = main(["probe", "imu", "--port", emu.port, "--seconds", "0.4",
                     "--set", "sensors.imu.counter_direction=up"])
    assert code == 0
    assert "the count direction looks wrong" in capsys.readouterr().out


def test_probe_imu_without_device_fails_clearly(capsys, tmp_path):
    code = main(["probe", "imu", "--port", str(tmp_path / "ttyUSB7"), "--seconds", "0.1"])
    assert code == 1
    assert "probe imu: FAILED:" in capsys.readouterr().err


def test_probe_gps_nmea(capsys):
    epochs = [NmeaEpoch(i * 100_000_000, 58.4 + 1e-5 * i, 15.6, 90.0) for i in range(12)]
    with NmeaEmulator(epochs, baud=115200) as emu:
        code = main(["probe", "gps", "--type", "nmea", "--port", emu.port, "--baud", "115200", "--seconds", "0.8"])
    out = capsys.readouterr().out
    assert code == 0
    assert "sentences: GPGGA" in out and "GPGST" in out
    assert "t [s],lat [deg],lon [deg]" in out and ",GST,9" in out
    assert "counts: " in out and "fixes" in out


def test_probe_camera_on_a_video_file_and_without_a_camera(capsys, tmp_path):
    path = tmp_path / "cam.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 7.5, (64, 48))
    for k in range(5):
        writer.write(np.full((48, 64, 3), 30 * k, np.uint8))
    writer.release()
    assert main(["probe", "camera", "--type", "opencv", "--port", str(path), "--seconds", "1"]) == 0
    out = capsys.readouterr().out
    assert "t [s],seq,width,height,mean intensity" in out and "\n0.0000,1,64,48," in out
    assert main(["probe", "camera", "--type", "opencv", "--port", str(tmp_path / "none.avi"), "--seconds", "0.1"]) == 1
    assert "FAILED: OpenCV could not open" in capsys.readouterr().err
