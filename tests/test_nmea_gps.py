"""NMEA GPS driver against the NMEA receiver emulator on a pseudo-terminal."""

from __future__ import annotations

import math
import time

import numpy as np
import pymap3d
import pytest

from vtolpose.drivers.files.dataset import Dataset, DatasetWriter, GpsSeries
from vtolpose.drivers.emulators import NmeaEmulator, NmeaEpoch
from vtolpose.drivers.emulators.nmea import nmea_sentence
from vtolpose.drivers.gps.common import VDOP_PER_HDOP, LocalNed, dop_sigmas
from vtolpose.drivers.gps.nmea import NmeaConfig, NmeaGps
from vtolpose.estimator.core.calibration import Calibration, GpsCalibration, ImuCalibration, ImuNoise

ORIGIN = (58.3975, 15.5762, 95.0)


def run(emulator: NmeaEmulator, config: NmeaConfig, drain_s: float = 0.3) -> tuple[list, NmeaGps]:
    """Open the port, then let the receiver talk (opening a port discards what came before)."""
    gps = NmeaGps(config)
    gps.open()
    emulator.start()
    try:
        out, start, done = [], time.monotonic(), None
        while time.monotonic() - start < 10.0:
            out += gps.read(0.05)
            if emulator.finished.is_set():
                done = done or time.monotonic()
                if time.monotonic() - done > drain_s:
                    break
    finally:
        gps.close()
        emulator.stop()
    return out, gps


def write_gps_dataset(root, n: int = 20) -> Dataset:
    t = 2_000_000_000 + np.arange(n, dtype=np.int64) * 200_000_000
    s = np.arange(n) * 0.2
    p = np.column_stack([30.0 * np.sin(0.3 * s), 12.0 * s, -5.0 - 0.5 * s])
    cal = Calibration(ImuCalibration(100.0, ImuNoise.isotropic(1e-4, 1e-5, 1e-3, 1e-4)), GpsCalibration(origin_lla=ORIGIN))
    writer = DatasetWriter(root)
    writer.write_calibration(cal, "gps", "test")
    writer.write_gps(GpsSeries(t, p, np.full(n, 0.4), np.full(n, 0.9)), geodetic_origin=ORIGIN)
    return Dataset.open(root)


def test_sentence_checksum_and_geodetic_helpers():
    assert nmea_sentence("GPGGA", ["x"]) == b"$GPGGA,x*" + f"{ord('G') ^ ord('P') ^ ord('G') ^ ord('G') ^ ord('A') ^ ord(',') ^ ord('x'):02X}".encode() + b"\r\n"
    sh, sv = dop_sigmas(1.2, None, 5.0)
    assert sh == pytest.approx(1.2 * 5.0 / math.sqrt(2)) and sv == pytest.approx(VDOP_PER_HDOP * 1.2 * 5.0)
    local = LocalNed()
    assert np.allclose(local(58.0, 15.0, 10.0), 0.0) and local.origin == (58.0, 15.0, 10.0)
    with pytest.raises(ValueError, match="lat"):
        LocalNed((91.0, 0.0, 0.0))


def test_dataset_fixes_round_trip_with_gst_sigmas(tmp_path):
    dataset = write_gps_dataset(tmp_path)
    truth = dataset.gps()
    emu = NmeaEmulator.from_dataset(tmp_path, baud=115200, speed=8.0)
    readings, gps = run(emu, NmeaConfig(emu.port, baud=115200, origin=ORIGIN))
    assert len(readings) == len(truth.t_ns)
    p = np.array([r.fix.p_ned for r in readings])
    assert np.max(np.abs(p - truth.p_ned)) < 1e-3  # 1e-7 arc-minutes in the sentences: 0.2 mm
    assert all(r.sigma_source == "GST" for r in readings)
    assert [r.fix.sigma_h for r in readings] == pytest.approx(truth.sigma_h, abs=1e-3)
    assert [r.fix.sigma_v for r in readings] == pytest.approx(truth.sigma_v, abs=1e-3)
    assert [r.alt_m for r in readings] == pytest.approx(
        pymap3d.ned2geodetic(*truth.p_ned.T, *ORIGIN)[2], abs=1e-3)  # MSL + geoid separation
    t = np.array([r.fix.t_ns for r in readings])
    assert np.all(np.diff(t) > 0)
    assert np.median(np.diff(t)) == pytest.approx(0.2e9 / 8.0, rel=0.3)  # host clock, 8x speed
    assert gps.counts["fixes"] == 20 and sum(gps.counts[k] for k in ("checksum", "truncated", "no_fix")) == 0
    assert {"GPGGA", "GPRMC", "GPGSA", "GPGST"} <= set(gps.sentence_types)


def test_bad_sentences_are_counted_and_skipped():
    epochs = [NmeaEpoch(i * 100_000_000, 58.4 + i * 1e-6, 15.6 - i * 2e-6, 90.0 + 0.1 * i,
                        quality=0 if i == 7 else 1) for i in range(14)]

    def mangle(i: int, kind: str, line: bytes) -> bytes:
        if i == 3 and kind == "GGA":
            return line[:-4] + (b"00" if line[-4:-2] != b"00" else b"11") + b"\r\n"  # wrong checksum
        if i == 5 and kind == "GGA":
            return line[:25]  # cut off: runs into the next sentence
        if i == 9 and kind == "GGA":
            return line[:-5] + b"\r\n"  # checksum missing
        if i == 10 and kind == "GST":
            return b"\x00\xff garbage \xfe\r\n"
        return line

    emu = NmeaEmulator(epochs, baud=115200, speed=4.0, mangle=mangle)
    readings, gps = run(emu, NmeaConfig(emu.port, baud=115200, origin=(58.4, 15.6, 90.0), uere_m=5.0))
    got = {round((r.lat_deg - 58.4) / 1e-6) for r in readings}
    assert got == set(range(14)) - {3, 5, 7, 9}
    assert gps.counts["checksum"] == 1 and gps.counts["no_fix"] == 1
    assert gps.counts["truncated"] == 2 and gps.counts["garbled"] == 1
    by_epoch = {round((r.lat_deg - 58.4) / 1e-6): r for r in readings}
    assert by_epoch[10].sigma_source == "DOP"  # its GST was lost: HDOP/VDOP x UERE instead
    assert by_epoch[10].fix.sigma_h == pytest.approx(0.9 * 5.0 / math.sqrt(2), rel=1e-6)
    assert by_epoch[10].fix.sigma_v == pytest.approx(1.4 * 5.0, rel=1e-6)
    assert by_epoch[11].sigma_source == "GST"


def test_receiver_without_gst_gets_dop_sigmas_and_first_fix_origin():
    epochs = [NmeaEpoch(i * 100_000_000, 58.4 + i * 1e-5, 15.6, 90.0, hdop=1.1, vdop=1.7) for i in range(8)]
    emu = NmeaEmulator(epochs, baud=115200, speed=2.0, sentences=("RMC", "GGA", "GSA"))
    readings, gps = run(emu, NmeaConfig(emu.port, baud=115200, uere_m=3.0))
    assert len(readings) == 8 and all(r.sigma_source == "DOP" for r in readings)
    assert readings[0].fix.p_ned == pytest.approx([0.0, 0.0, 0.0], abs=1e-9)  # origin: the first fix
    assert gps.local.origin == pytest.approx((58.4, 15.6, 90.0))
    assert readings[3].fix.p_ned[0] == pytest.approx(3e-5 * 111_360, rel=0.01)
    assert readings[1].fix.sigma_v == pytest.approx(1.7 * 3.0)


def test_lost_port_is_retried_without_raising(tmp_path):
    epochs = [NmeaEpoch(i * 100_000_000, 58.4, 15.6, 90.0) for i in range(200)]
    emu = NmeaEmulator(epochs, baud=115200)
    gps = NmeaGps(NmeaConfig(emu.port, baud=115200, silence_timeout_s=0.2, reconnect_min_s=0.05))
    gps.open()
    emu.start()
    got = []
    for _ in range(8):
        got += gps.read(0.05)
    emu.stop()
    for _ in range(8):
        assert gps.read(0.05) == []
    assert got and (gps.counts["link_errors"] + gps.counts["silences"]) >= 1
    assert gps.status.startswith("reconnecting")
    gps.close()
