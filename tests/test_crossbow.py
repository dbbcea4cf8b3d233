"""Crossbow IMU400CC: packet codec, stream framing, and the real driver against the emulator on a pty."""

from __future__ import annotations

import math
import random
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vtolpose.drivers.imu.crossbow import (
    PACKET_LEN, CrossbowScale, PacketFramer, TimeCounter, checksum, decode_packet, encode_packet,
)
from vtolpose.drivers.imu.crossbow_serial import CrossbowConfig, CrossbowImu, parse_serial_reply, parse_version_reply
from vtolpose.drivers.files.dataset import Dataset, DatasetWriter, ImuSeries
from vtolpose.drivers.emulators import Imu400Emulator
from vtolpose.drivers.links.serial_link import DeviceError
from vtolpose.estimator.core.calibration import Calibration, ImuCalibration, ImuNoise
from vtolpose.estimator.core.rotation import quat_from_euler, quat_to_rot

SCALE = CrossbowScale(100.0, 2.0)
COUNTER = TimeCounter(7.9e-7, counts_down=True)
STEP = round(0.008 / COUNTER.tick_s)  # ticks per packet at 125 Hz
WORD = st.integers(-32768, 32767)


def random_series(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """125 Hz manoeuvres over most of the IMU400CC-100's range (±150 °/s, ±3 g full scale):
    random sinusoids with noise, smooth as filtered IMU output is."""
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=np.int64) * 8_000_000 + 1_000_000_000
    s = (t - t[0])[:, None] * 1e-9
    freq, phase = rng.uniform(0.2, 3.0, (2, 3)), rng.uniform(0, 2 * np.pi, (2, 3))
    gyro = 2.0 * np.sin(2 * np.pi * freq[0] * s + phase[0]) + rng.normal(0, 0.01, (n, 3))
    accel = 25.0 * np.sin(2 * np.pi * freq[1] * s + phase[1]) + rng.normal(0, 0.05, (n, 3))
    return t, gyro, accel


def imu_config(port: str, **kw) -> CrossbowConfig:
    settings_ = dict(scale=SCALE, counter=COUNTER, reply_timeout_s=0.2, silence_timeout_s=0.2,
                     reconnect_min_s=0.05, reconnect_max_s=0.2)
    settings_.update(kw)
    return CrossbowConfig(port, **settings_)


def collect(imu: CrossbowImu, emu: Imu400Emulator, limit_s: float = 10.0, drain_s: float = 0.1) -> tuple[list, float]:
    """Read until the emulator has sent everything (plus a short drain); returns readings and
    the longest single ``read`` call (a stall would show there)."""
    out, longest = [], 0.0
    start = time.monotonic()
    done_at = None
    while time.monotonic() - start < limit_s:
        t0 = time.monotonic()
        out += imu.read(0.05)
        longest = max(longest, time.monotonic() - t0)
        if emu.finished.is_set():
            done_at = done_at or time.monotonic()
            if time.monotonic() - done_at > drain_s:
                break
    return out, longest


def words_of(reading) -> tuple[int, ...]:
    return (*SCALE.encode(reading.gyro, reading.accel, reading.temperature_c), reading.counter)


# -- codec ----------------------------------------------------------------------------------------
@given(st.tuples(*[WORD] * 7, st.integers(0, 65535)))
def test_packet_round_trips_and_any_single_byte_change_is_caught(words):
    packet = encode_packet(words)
    assert len(packet) == PACKET_LEN and packet[0] == 0xFF and packet[17] == checksum(packet[1:17])
    assert decode_packet(packet) == words
    for i in range(1, PACKET_LEN):
        broken = bytearray(packet)
        broken[i] ^= 0x10
        assert decode_packet(broken) is None


def test_scaling_follows_the_model_ranges():
    # A word of 2^15 / 1.5 is the model's range: RR deg/s and GR g.
    w = round(2**15 / 1.5)
    gyro, accel, temperature = SCALE.decode((w, -w, 0, w, 0, -w, 2048, 0))
    assert gyro == pytest.approx([math.radians(100.0), -math.radians(100.0), 0.0], rel=1e-4)
    assert accel == pytest.approx([2 * 9.80665, 0.0, -2 * 9.80665], rel=1e-4)
    assert temperature == pytest.approx(44.44 * (2048 * 5 / 4096 - 1.375))
    wide = CrossbowScale(200.0, 4.0)
    assert wide.decode((w, 0, 0, w, 0, 0, 0, 0))[0][0] == pytest.approx(math.radians(200.0), rel=1e-4)
    assert SCALE.encode(np.full(3, 1e3), np.full(3, -1e3), 25.0)[:6] == (32767,) * 3 + (-32768,) * 3


def test_counter_direction_and_wrap():
    assert TimeCounter(1e-6, counts_down=False).delta(65530, 4) == 10
    assert TimeCounter(1e-6, counts_down=True).delta(4, 65530) == 10
    assert TimeCounter(1e-6, counts_down=True).value(3) == 65533


def test_identity_replies_are_parsed_and_checked():
    text = b"IMU400CC-100 v3"
    assert parse_version_reply(b"\xff" + text + bytes([checksum(text)])) == ("IMU400CC-100 v3", None)
    assert parse_version_reply(b"\xff" + text + b"\x00")[1] == "version reply checksum mismatch"
    assert parse_version_reply(b"")[0] is None
    number = (123456789).to_bytes(4, "big")
    assert parse_serial_reply(b"H\xff" + number + bytes([checksum(number)])) == 123456789
    assert parse_serial_reply(b"\xff" + number + b"\x00") is None


# -- framing (pure, fast, property-style) ---------------------------------------------------------
def corrupt_stream(n: int, rng: random.Random, rate: float) -> tuple[bytes, list[tuple[int, ...]], set[int]]:
    """``n`` packets at 125 Hz with random words; some corrupted. Returns the stream, every
    packet's words, and the indices whose own 18 bytes were damaged."""
    stream, words, damaged = bytearray(), [], set()
    inertial, temperature = [rng.randint(-20000, 20000) for _ in range(6)], 1600
    for i in range(n):
        # Rates and accelerations move by up to ~2 % of full scale per packet, temperature drifts.
        inertial = [max(-32768, min(32767, v + rng.randint(-600, 600))) for v in inertial]
        temperature += rng.randint(-3, 3)
        counter = COUNTER.value(i * STEP + rng.randint(-1, 1))
        w = (*inertial, temperature, counter)
        words.append(w)
        packet = bytearray(encode_packet(w))
        kind = rng.choice(("flip", "drop", "ff_inside", "ff_between", "garbage")) if i >= 10 and rng.random() < rate else None
        if kind == "flip":
            packet[rng.randrange(PACKET_LEN)] ^= 1 << rng.randrange(8)
        elif kind == "drop":
            del packet[rng.randrange(PACKET_LEN)]
        elif kind == "ff_inside":
            packet.insert(rng.randrange(1, PACKET_LEN), 0xFF)
        elif kind == "ff_between":
            packet.append(0xFF)
        elif kind == "garbage":
            stream += bytes(rng.choice((0xFF, rng.randrange(256))) for _ in range(rng.randint(1, 60)))
        if kind in ("flip", "drop", "ff_inside"):
            damaged.add(i)
        stream += packet
    return bytes(stream), words, damaged


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.integers(0, 2**32 - 1))
def test_framer_delivers_every_intact_packet_and_nothing_else(seed):
    rng = random.Random(seed)
    stream, words, damaged = corrupt_stream(120, rng, rate=0.15)
    framer = PacketFramer(COUNTER, byte_time_ns=260_417)
    frames, pos, t = [], 0, 0
    while pos < len(stream):  # random chunking, as reads would cut it
        size = rng.randint(1, 60)
        t += size * 260_417
        frames += framer.feed(stream[pos:pos + size], t)
        pos += size
    got = [f.words for f in frames]
    intact = [w for i, w in enumerate(words) if i not in damaged]
    assert set(got) <= set(words), "a false header was taken for a packet"
    assert set(intact[:-1]) <= set(got), "an intact packet was lost"  # the last waits for a successor
    assert got == sorted(got, key=words.index), "packets out of order"
    assert all(b.t_ns > a.t_ns for a, b in zip(frames, frames[1:]))
    # Every damaged packet costs sync once (adjacent ones may share a loss); the time counter
    # accounts for exactly the packets missing between delivered ones. (A damaged packet can
    # still come through whole: e.g. 0xFF inserted before a checksum that happens to be 0xFF.)
    delivered = sorted(words.index(w) for w in got)
    runs = sum(1 for i in damaged if i - 1 not in damaged)
    assert framer.stats.bad >= runs - (len(words) - 1 in damaged)
    assert framer.stats.lost == (delivered[-1] - delivered[0] + 1) - len(delivered)
    # Framing depends on the bytes only, not on how they were chunked.
    whole = PacketFramer(COUNTER, byte_time_ns=260_417).feed(stream, t)
    assert [f.words for f in whole] == got


def test_framer_survives_pure_garbage_and_bounded_memory():
    framer = PacketFramer(COUNTER, byte_time_ns=1000)
    rng = random.Random(3)
    junk = bytes(rng.choice((0xFF, 0x00, rng.randrange(256))) for _ in range(20_000))
    for k in range(0, len(junk), 512):
        framer.feed(junk[k:k + 512], k)
    assert len(framer._buf) < 2 * PACKET_LEN
    assert framer.stats.good <= 2 and framer.stats.skipped_bytes > 19_000


# -- the driver against the emulator --------------------------------------------------------------
def write_imu_dataset(root: Path, n: int, R_BI: np.ndarray) -> Dataset:
    t, gyro, accel = random_series(n, seed=11)
    cal = Calibration(ImuCalibration(125.0, ImuNoise.isotropic(1e-4, 1e-5, 1e-3, 1e-4), R_BI=R_BI))
    writer = DatasetWriter(root)
    writer.write_calibration(cal, "imu-roundtrip", "test")
    writer.write_imu(ImuSeries(t, gyro, accel))
    return Dataset.open(root)


def test_dataset_samples_round_trip_through_emulator_and_driver(tmp_path):
    R_BI = quat_to_rot(quat_from_euler(0.1, -0.2, 1.3))
    dataset = write_imu_dataset(tmp_path, 100, R_BI)
    raw, body = dataset.imu_raw(), dataset.imu()
    with Imu400Emulator.from_dataset(tmp_path, scale=SCALE, counter=COUNTER, speed=1.6) as emu:
        imu = CrossbowImu(imu_config(emu.port, R_BI=R_BI))
        identity = imu.open()
        readings, _ = collect(imu, emu)
        imu.close()
        time.sleep(0.05)
        assert emu.received.endswith(b"P"), "close must stop continuous mode"
    assert identity.version == "IMU400CC-100 emulated" and identity.serial_number == 0x0A1B2C3D
    assert len(readings) == len(raw.t_ns)
    gyro = np.array([r.gyro for r in readings])
    accel = np.array([r.accel for r in readings])
    assert np.max(np.abs(gyro - raw.gyro)) <= SCALE.gyro_lsb / 2 + 1e-12
    assert np.max(np.abs(accel - raw.accel)) <= SCALE.accel_lsb / 2 + 1e-12
    assert np.allclose([r.sample.gyro for r in readings], body.gyro, atol=SCALE.gyro_lsb)
    assert np.allclose([r.sample.accel for r in readings], body.accel, atol=SCALE.accel_lsb)
    t = np.array([r.t_ns for r in readings])
    assert np.all(np.diff(t) > 0)
    latency = t - np.array([p.sent_ns for p in emu.sent])  # host time of arrival vs of sending
    assert -2e6 < np.median(latency) < 15e6
    ticks = np.array([r.device_ticks for r in readings])
    assert np.all(np.abs(np.diff(ticks) - STEP) <= 1)  # counter unwrapped across its ~6-packet wrap
    counts = imu.counts()
    assert counts["good"] == 100 and counts["bad"] == counts["lost"] == counts["skipped_bytes"] == 0


def test_corrupted_stream_and_a_reboot_lose_only_the_damaged_packets():
    n, rng, damaged = 280, random.Random(7), set()
    t, gyro, accel = random_series(n, seed=5)
    silence_after = 150
    clean = set(range(12)) | set(range(silence_after - 1, silence_after + 4)) | {n - 1}

    def mangle(i: int, packet: bytes) -> bytes:
        if i in clean or rng.random() > 0.12:
            return packet
        kind, data = rng.choice(("flip", "drop", "ff_inside", "ff_between", "garbage")), bytearray(packet)
        if kind == "flip":
            data[rng.randrange(PACKET_LEN)] ^= 1 << rng.randrange(8)
        elif kind == "drop":
            del data[rng.randrange(PACKET_LEN)]
        elif kind == "ff_inside":
            data.insert(rng.randrange(1, PACKET_LEN), 0xFF)
        elif kind == "ff_between":
            data.append(0xFF)
        else:
            data[:0] = bytes(rng.randrange(256) for _ in range(rng.randint(5, 50)))
        if kind in ("flip", "drop", "ff_inside"):
            damaged.add(i)
        return bytes(data)

    with Imu400Emulator(t, gyro, accel, scale=SCALE, counter=COUNTER, speed=2.0, mangle=mangle,
                        silences={silence_after: (0.6, True)}) as emu:
        imu = CrossbowImu(imu_config(emu.port, silence_timeout_s=0.3))
        imu.open()
        readings, longest = collect(imu, emu, drain_s=0.1)
        imu.close()
    sent = {p.index: p.words for p in emu.sent}
    assert len(sent) == n
    got = [words_of(r) for r in readings]
    good = [w for i, w in sent.items() if i not in damaged]
    assert len(damaged) >= 15
    assert set(got) <= set(sent.values()), "a corrupted or false packet was delivered"
    assert set(good) <= set(got), f"lost {len(set(good) - set(got))} intact packets"
    counts = imu.counts()
    runs = sum(1 for i in damaged if i - 1 not in damaged)
    assert runs <= counts["bad"] <= runs + n // 5  # each damage costs sync once; inserted bytes may too
    # The time counter accounts for every packet missing between two delivered in one session
    # (a session restarts the unwrapped device time at 0).
    index = {w: i for i, w in sent.items()}
    sessions = np.cumsum([r.device_ticks == 0 for r in readings])
    missing = 0
    for s in set(sessions):
        numbers = [index[w] for w, k in zip(got, sessions) if k == s]
        missing += numbers[-1] - numbers[0] + 1 - len(numbers)
    assert counts["lost"] == missing and missing >= len(damaged) // 2
    assert counts["silences"] >= 1 and counts["connects"] >= 2
    assert longest < 1.0, "read() stalled"


def test_stream_resumes_after_the_cable_is_pulled_mid_stream():
    t, gyro, accel = random_series(100, seed=2)
    with Imu400Emulator(t, gyro, accel, scale=SCALE, counter=COUNTER, speed=2.0,
                        silences={40: (0.4, False)}) as emu:  # device keeps streaming when back
        imu = CrossbowImu(imu_config(emu.port))
        imu.open()
        readings, _ = collect(imu, emu)
        imu.close()
    got = {words_of(r) for r in readings}
    sent = [p.words for p in emu.sent]
    assert set(sent[:41]) <= got
    assert sent[-1] in got  # streaming again after the reconnect
    assert imu.counts()["silences"] >= 1 and imu.counts()["connects"] >= 2


def test_no_device_gives_a_clear_error_and_read_keeps_retrying_without_raising(tmp_path):
    t, gyro, accel = random_series(10, seed=1)
    with Imu400Emulator(t, gyro, accel) as emu:
        emu.go_silent(5.0)  # powered off: the port exists, nothing answers
        imu = CrossbowImu(imu_config(emu.port))
        with pytest.raises(DeviceError, match="ping"):
            imu.open()
    imu = CrossbowImu(imu_config(str(tmp_path / "ttyUSB9")))
    start = time.monotonic()
    for _ in range(6):
        assert imu.read(0.05) == []
    assert time.monotonic() - start < 1.0
    assert imu.status.startswith("reconnecting") and "ttyUSB9" in imu.status


def test_unplugged_port_is_counted_and_retried():
    t, gyro, accel = random_series(400, seed=3)
    emu = Imu400Emulator(t, gyro, accel, scale=SCALE, counter=COUNTER).start()
    imu = CrossbowImu(imu_config(emu.port))
    imu.open()
    got = []
    for _ in range(5):
        got += imu.read(0.05)
    emu.stop()  # the USB adapter is gone
    for _ in range(8):
        imu.read(0.05)
    imu.close()
    assert got and imu.status == "closed"
    counts = imu.counts()
    assert counts["link_errors"] + counts["silences"] >= 1


def test_close_from_another_thread_ends_reads_quietly(caplog):
    t, gyro, accel = random_series(300, seed=4)
    with Imu400Emulator(t, gyro, accel, scale=SCALE, counter=COUNTER) as emu:
        imu = CrossbowImu(imu_config(emu.port))
        imu.open()
        got, errors = [], []

        def reader() -> None:
            try:
                while imu.status != "closed":
                    got.extend(imu.read(0.5))
            except Exception as exc:  # noqa: BLE001 - the point is that nothing escapes
                errors.append(exc)

        thread = threading.Thread(target=reader)
        thread.start()
        time.sleep(0.2)
        imu.close()
        thread.join(2.0)
        time.sleep(0.05)
        assert emu.received.endswith(b"P")
    assert not thread.is_alive() and not errors and got
    assert not [r for r in caplog.records if "reconnecting" in r.getMessage()]
