"""Property-based tests of every parser of outside input: only clear errors or counted skips come out.

Covered: the Crossbow IMU400CC framer and reply parsers, the NMEA and MAVLink GPS drivers, dataset
CSV rows (``parse_time_ns``, ``read_numeric_csv``, the camera frame index, ``Dataset.gps``), TUM /
EuRoC trajectories, ``dataset.yaml`` calibration, the configuration loader and ``--fault`` specs.
Each parser gets arbitrary input (nothing but its documented error may come out) and valid input
with corruption spliced in (everything intact still comes out with the values that went in, and
the skips are counted).

CI runs derandomized examples, so a failure is a regression and never luck. For a local fuzzing
session, ``VTOLPOSE_FUZZ=20 pytest tests/test_parser_properties.py`` runs 20 times as many examples,
freshly random each time.
"""

from __future__ import annotations

import copy
import math
import os
import random
from collections import deque
from decimal import Decimal
from pathlib import Path
from typing import Any, Callable
from unittest import mock

import numpy as np
import pytest
import yaml
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from vtolpose import config
from vtolpose.config import ConfigError, load_config
from vtolpose.config.schema import SCHEMA
from vtolpose.drivers.files.calibration_yaml import CalibrationError, calibration_from_yaml, calibration_to_yaml
from vtolpose.drivers.imu.crossbow import PACKET_LEN, CrossbowScale, PacketFramer, TimeCounter, checksum, decode_packet, encode_packet
from vtolpose.drivers.imu.crossbow_serial import parse_serial_reply, parse_version_reply
from vtolpose.drivers.files.csvio import parse_time_ns, read_numeric_csv, seconds_text
from vtolpose.drivers.files.dataset import Dataset, DatasetWriter
from vtolpose.drivers.emulators.nmea import nmea_sentence
from vtolpose.drivers.files.frames_csv import read_frame_index
from vtolpose.drivers.gps.mavlink_gps import MavlinkGps, MavlinkGpsConfig, mavutil
from vtolpose.drivers.gps.nmea import MAX_LINE, NmeaConfig, NmeaGps
from vtolpose.drivers.files.tum import read_tum, write_tum
from vtolpose.estimator.core.calibration import Calibration, CameraCalibration, GpsCalibration, ImuCalibration, ImuNoise
from vtolpose.estimator.core.rotation import quat_to_rot
from vtolpose.service.replay.faults import FAULT_KINDS, MAX_CLOCK_STEP_S, FaultError, parse_fault, parse_faults

_FUZZ = int(os.environ.get("VTOLPOSE_FUZZ", "0"))


def fuzz(examples: int) -> settings:
    """``examples`` derandomized examples (CI), or ``examples × VTOLPOSE_FUZZ`` random ones."""
    return settings(max_examples=examples * max(_FUZZ, 1), deadline=None, database=None, derandomize=not _FUZZ)


@pytest.fixture(scope="module")
def scratch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One folder for the files every example rewrites (hypothesis runs many examples per test)."""
    return tmp_path_factory.mktemp("parser_fuzz")


def cut(data: bytes, sizes: list[int]) -> list[bytes]:
    """``data`` in pieces of the given sizes (cycled), as serial reads would return it."""
    out, pos, k = [], 0, 0
    while pos < len(data):
        size = sizes[k % len(sizes)] if sizes else len(data)
        out.append(data[pos:pos + size])
        pos, k = pos + size, k + 1
    return out


# ================================================================================================
# Crossbow IMU400CC
# ================================================================================================
SCALE = CrossbowScale(100.0, 2.0)
COUNTER = TimeCounter(7.9e-7, counts_down=True)
STEP = round(0.008 / COUNTER.tick_s)    # counter ticks per packet at 125 Hz
BYTE_NS = 260_417                       # one byte at 38400 baud
CLEAN_START = PacketFramer.MIN_STEPS + 2  # packets it takes to learn the counter step


@fuzz(200)
@given(st.binary(max_size=2 * PACKET_LEN))
def test_crossbow_decode_packet_is_an_exact_inverse_or_none(data: bytes) -> None:
    words = decode_packet(data)
    if words is not None:
        assert encode_packet(words) == data


@fuzz(200)
@given(st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3), st.lists(st.floats(-25.0, 25.0), min_size=3, max_size=3),
       st.floats(-40.0, 85.0))
def test_crossbow_si_values_round_trip_within_half_a_count(gyro: list, accel: list, temperature: float) -> None:
    words = (*SCALE.encode(np.array(gyro), np.array(accel), temperature), 0x1234)
    g, a, c = SCALE.decode(decode_packet(encode_packet(words)))
    assert np.all(np.abs(g - gyro) <= SCALE.gyro_lsb / 2 * (1 + 1e-9))
    assert np.all(np.abs(a - accel) <= SCALE.accel_lsb / 2 * (1 + 1e-9))
    assert abs(c - temperature) <= 44.44 * 5.0 / 4096.0 / 2 * (1 + 1e-9)


def frame_stream(framer: PacketFramer, stream: bytes, sizes: list[int]) -> list:
    """Feed ``stream`` in pieces, each dated when its last byte arrives on a 38400-baud line."""
    frames, end = [], 0
    for piece in cut(stream, sizes):
        end += len(piece)
        frames += framer.feed(piece, end * BYTE_NS)
    return frames


def check_framer_invariants(framer: PacketFramer, frames: list, stream: bytes) -> None:
    """Nothing invented, order kept, every byte accounted for as a packet or as skipped."""
    assert all(encode_packet(f.words) in stream for f in frames)
    assert all(b.t_ns > a.t_ns for a, b in zip(frames, frames[1:]))
    framer.reset()  # whatever still waited in the buffer counts as skipped now
    assert framer.stats.skipped_bytes + PACKET_LEN * framer.stats.good == len(stream)
    assert framer.stats.good == len(frames)


PIECE = st.one_of(
    st.lists(st.sampled_from([0xFF, 0x00]) | st.integers(0, 255), max_size=40).map(bytes),  # 0xFF-rich noise
    st.tuples(*[st.integers(-32768, 32767)] * 7, st.integers(0, 65535)).map(encode_packet),  # a packet, any words
)


@fuzz(200)
@given(st.lists(PIECE, max_size=30), st.lists(st.integers(1, 64), max_size=8))
def test_crossbow_framer_takes_any_bytes_and_accounts_for_each(pieces: list[bytes], cuts: list[int]) -> None:
    stream = b"".join(pieces)
    framer = PacketFramer(COUNTER, BYTE_NS)
    frames = frame_stream(framer, stream, cuts)
    whole = PacketFramer(COUNTER, BYTE_NS).feed(stream, len(stream) * BYTE_NS)
    assert [f.words for f in whole] == [f.words for f in frames], "framing depended on how reads cut the bytes"
    check_framer_invariants(framer, frames, stream)


CORRUPTION = st.one_of(
    st.tuples(st.just("garbage"), st.binary(min_size=1, max_size=40)),       # bytes before the packet
    st.tuples(st.just("flip"), st.integers(0, PACKET_LEN - 1), st.integers(1, 255)),
    st.tuples(st.just("drop"), st.integers(0, PACKET_LEN - 1)),
    st.tuples(st.just("insert"), st.integers(1, PACKET_LEN - 1), st.integers(0, 255)),
    st.tuples(st.just("truncate"), st.integers(1, PACKET_LEN - 1)),
    st.tuples(st.just("lose"),),                                               # the packet never sent
)


@st.composite
def imu_stream(draw: st.DrawFn) -> tuple[list[tuple[int, ...]], dict[int, tuple]]:
    """Packets of a smooth 125 Hz signal (rates and accelerations move by up to ~2 % of full scale
    per packet, temperature drifts, the counter jitters by a tick), and corruption after a clean start."""
    n = draw(st.integers(CLEAN_START + 2, 60))
    rng = random.Random(draw(st.integers(0, 2**32 - 1)))
    inertial = [draw(st.integers(-3000, 3000)) if draw(st.booleans()) else rng.randint(-30000, 30000) for _ in range(6)]
    temperature, counter0 = draw(st.integers(-2000, 4000)), draw(st.integers(0, 65535))
    words = []
    for i in range(n):
        inertial = [max(-32768, min(32767, v + rng.randint(-600, 600))) for v in inertial]
        temperature += rng.randint(-3, 3)
        words.append((*inertial, temperature, COUNTER.value(counter0 + i * STEP + rng.randint(-1, 1))))
    events = draw(st.dictionaries(st.integers(CLEAN_START, n - 1), CORRUPTION, max_size=8))
    return words, events


def corrupted_bytes(words: list[tuple[int, ...]], events: dict[int, tuple]) -> tuple[bytes, set[int], set[int]]:
    """The byte stream, the packets whose own bytes were damaged, and those never sent."""
    stream, damaged, missing = bytearray(), set(), set()
    for i, w in enumerate(words):
        packet, event = bytearray(encode_packet(w)), events.get(i, ("none",))
        kind = event[0]
        if kind == "garbage":
            stream += event[1]
        elif kind == "flip":
            packet[event[1]] ^= event[2]
        elif kind == "drop":
            del packet[event[1]]
        elif kind == "insert":
            packet.insert(event[1], event[2])
        elif kind == "truncate":
            del packet[event[1]:]
        elif kind == "lose":
            packet = bytearray()
            missing.add(i)
        if kind in ("flip", "drop", "insert", "truncate"):
            damaged.add(i)
        stream += packet
    return bytes(stream), damaged, missing


@fuzz(150)
@given(imu_stream(), st.lists(st.integers(1, 80), max_size=6))
def test_crossbow_framer_keeps_every_intact_packet_amid_corruption(case: tuple, cuts: list[int]) -> None:
    """An intact packet with an intact neighbour directly before or after it is always delivered.

    (An isolated one may need the counter to vouch for it, which a long loss can defeat.) The one
    exception is inherent to the protocol: a damaged packet can come out whole by borrowing bytes
    of the next one (a dropped checksum of 0xFF is supplied by the next header), so each damaged
    packet delivered may cost one intact packet. Nothing is ever invented.
    """
    words, events = case
    stream, damaged, missing = corrupted_bytes(words, events)
    framer = PacketFramer(COUNTER, BYTE_NS)
    frames = frame_stream(framer, stream, cuts)
    got = [f.words for f in frames]
    assert set(got) <= set(words), "a packet that was never sent came out"
    delivered = [words.index(w) for w in got]
    assert delivered == sorted(delivered)

    def clean(i: int) -> bool:
        return 0 <= i < len(words) and i not in damaged and i not in missing

    def joined(a: int, b: int) -> bool:  # b's header directly after a's checksum
        return clean(a) and clean(b) and b not in events

    sent = [i for i in range(len(words)) if i not in missing]
    required = [i for i in sent[:-1] if clean(i) and (joined(i - 1, i) or joined(i, i + 1))]  # the last waits
    lost = [i for i in required if i not in delivered]
    recovered = [i for i in damaged if i in delivered]
    assert len(lost) <= len(recovered), f"intact packets {lost} lost"
    # The counter accounts for the packets missing between delivered ones, as long as no gap
    # spans a whole counter wrap (6.5 packets here; longer gaps are ambiguous by design).
    span = delivered[-1] - delivered[0] + 1 - len(delivered) if delivered else 0
    if all((b - a) * STEP < 65536 for a, b in zip(delivered, delivered[1:])):
        assert framer.stats.lost == span
    check_framer_invariants(framer, frames, stream)


def test_crossbow_chance_checksum_before_the_counter_step_is_learned_is_refused() -> None:
    """Found by fuzzing: packet 4 cut after 12 bytes, plus the next packet's first 6, has a valid
    checksum (1 in 256). Before the counter step is learned only the temperature word can tell
    it is no packet; taken, it delivered garbage and swallowed packet 5."""
    words = [(-27694, 2088, -17792, 13206, 25903, 8423, -3, 0), (-27526, 1952, -17504, 13401, 25771, 8472, 0, 55408),
             (-27402, 2524, -17325, 13365, 25836, 8044, -2, 45282), (-27562, 1958, -16928, 12766, 26030, 7648, 1, 35156),
             (-27522, 2052, -17030, 12363, 25926, 8122, 1, 25027), (-26947, 1737, -17592, 11986, 25845, 8329, 1, 14900),
             (-27357, 1314, -17921, 12028, 25955, 7755, -2, 4773), (-27390, 1547, -17472, 11511, 26276, 7197, 0, 60184)]
    stream, _, _ = corrupted_bytes(words, {4: ("truncate", 12)})
    assert decode_packet(stream[4 * PACKET_LEN:5 * PACKET_LEN]) is not None  # the chance packet
    frames = PacketFramer(COUNTER, BYTE_NS).feed(stream, len(stream) * BYTE_NS)
    assert [f.words for f in frames] == words[:4] + words[5:]


@fuzz(200)
@given(st.binary(max_size=40), st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), min_size=1, max_size=30),
       st.integers(0, 2**32 - 1))
def test_crossbow_identity_replies_parse_or_say_why(noise: bytes, text: str, serial: int) -> None:
    version, note = parse_version_reply(noise)
    assert (version is None) == (note is not None and note.startswith("no version reply"))
    parse_serial_reply(noise)  # None or a number, never an exception
    prefix = noise.replace(b"\xff", b"")
    body = text.encode("ascii")
    assert parse_version_reply(prefix + b"\xff" + body + bytes([checksum(body)])) == (text.strip("\x00 \r\n"), None)
    number = serial.to_bytes(4, "big")
    assert parse_serial_reply(prefix + b"\xff" + number + bytes([checksum(number)])) == serial


# ================================================================================================
# NMEA GPS
# ================================================================================================
ORIGIN = (58.4, 15.6, 100.0)
UERE_M = 4.0
NMEA_SKIPS = ("garbled", "truncated", "checksum", "malformed")


class ScriptedLink:
    """Stands in for the serial port: hands out queued chunks, dated by the test's clock."""

    def __init__(self, port: str, baud: int, clock: Callable[[], int]) -> None:
        self.byte_time_ns = 10 * 1_000_000_000 // baud
        self.chunks: deque[bytes] = deque()
        self.is_open = False
        self._clock = clock

    def open(self) -> None:
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def read(self, timeout_s: float) -> tuple[bytes, int]:
        return (self.chunks.popleft() if self.chunks else b""), self._clock()


def nmea_readings(stream: bytes, sizes: list[int]) -> tuple[list, NmeaGps]:
    """Every fix the driver makes of ``stream``, read in chunks 10 ms apart (through any silence
    reconnects), then a wait long enough that no fix is left waiting for its GST."""
    now, links = [1_000_000_000], []

    def link(port: str, baud: int, clock: Callable[[], int]) -> ScriptedLink:
        links.append(ScriptedLink(port, baud, clock))
        return links[-1]

    with mock.patch("vtolpose.drivers.gps.nmea.SerialLink", link):
        gps = NmeaGps(NmeaConfig("scripted", 115200, uere_m=UERE_M, origin=ORIGIN), clock=lambda: now[0])
    gps.open()
    links[0].chunks.extend(cut(stream, sizes))
    readings = []
    for _ in range(2 * len(links[0].chunks) + 2):  # a read that reopens the port takes no chunk
        now[0] += 10_000_000
        readings += gps.read(0.0)
        if not links[0].chunks:
            break
    assert not links[0].chunks
    now[0] += 1_000_000_000
    return readings + gps.read(0.0), gps


def assert_plausible_fix(reading: Any) -> None:
    assert -90.0 <= reading.lat_deg <= 90.0 and -180.0 <= reading.lon_deg <= 180.0, reading
    assert math.isfinite(reading.alt_m) and np.all(np.isfinite(reading.fix.p_ned)), reading
    assert 0.0 < reading.fix.sigma_h < math.inf and 0.0 < reading.fix.sigma_v < math.inf, reading


def assert_lines_accounted(gps: NmeaGps) -> None:
    """Every line either parsed (counted by sentence type) or was counted as skipped."""
    assert gps.counts["lines"] <= sum(gps.counts[k] for k in NMEA_SKIPS) + sum(gps.sentence_types.values())


def one_field_off(valid: st.SearchStrategy[tuple], junk: st.SearchStrategy[tuple]) -> st.SearchStrategy[tuple]:
    """Fields that are all usable, or the same with one taken from ``junk`` (so that fixes come out
    often, and each way a field can be wrong is met on its own)."""
    return st.tuples(valid, junk, st.none() | st.integers(0, 99)).map(
        lambda t: tuple(j if t[2] is not None and i == t[2] % len(t[0]) else v for i, (v, j) in enumerate(zip(t[0], t[1]))))


def angle_text(degree_digits: int, limit: int, real: bool) -> st.SearchStrategy[tuple[str, float]]:
    """``(d)ddmm.mmmm`` text, of a real angle or of any digits (minutes up to 99), and the angle it spells."""
    degrees = st.integers(0, limit - 1) if real else st.integers(0, 10**degree_digits - 1)
    return st.tuples(degrees, st.integers(0, 59 if real else 99), st.integers(0, 9999)).map(
        lambda t: (f"{t[0]:0{degree_digits}d}{t[1]:02d}.{t[2]:04d}", t[0] + (t[1] + t[2] / 1e4) / 60.0))


NUMBER = st.floats(0.01, 500.0).map("{:.3f}".format)
DOP = st.floats(0.5, 5.0).map("{:.1f}".format)
JUNK_NUMBER = st.sampled_from(["", "nan", "inf", "-inf", "1e308", "1e400", "-0", "0", "0.0", "-5", "x", "99.99", "100"]) | \
    st.floats(allow_nan=False, allow_infinity=False).map("{:.6g}".format)
JUNK_UTC = st.sampled_from(["120000.20", "", "25xx00", "999999.99"])
GGA_FIELDS = one_field_off(
    st.tuples(st.just("120000.00"), angle_text(2, 90, True), st.sampled_from("NS"), angle_text(3, 180, True),
              st.sampled_from("EW"), st.sampled_from(["1", "2"]), NUMBER, DOP, NUMBER, NUMBER),
    st.tuples(JUNK_UTC, angle_text(2, 90, False), st.sampled_from(["", "X", "n"]), angle_text(3, 180, False),
              st.sampled_from(["", "Q", "e"]), st.sampled_from(["0", "", "x", "0.0", "-1"]), JUNK_NUMBER, JUNK_NUMBER,
              JUNK_NUMBER, JUNK_NUMBER))
NMEA_ANY = st.one_of(
    GGA_FIELDS.map(lambda f: ("GPGGA", [f[0], f[1][0], f[2], f[3][0], f[4], f[5], f[6], f[7], f[8], "M", f[9], "M", "", ""],
                              (f[1][1], f[3][1]))),
    one_field_off(st.tuples(st.just("120000.00"), *[NUMBER] * 7), st.tuples(JUNK_UTC, *[JUNK_NUMBER] * 7)).map(
        lambda f: ("GPGST", list(f), None)),
    one_field_off(st.tuples(*[DOP] * 17), st.tuples(*[JUNK_NUMBER] * 17)).map(lambda f: ("GPGSA", list(f), None)),
    st.tuples(JUNK_UTC | st.just("120000.00"), st.sampled_from(["A", "V", "", "x"])).map(
        lambda f: ("GPRMC", [*f, *[""] * 10], None)),
)


@fuzz(200)
@given(st.lists(NMEA_ANY, max_size=12), st.lists(st.integers(1, 90), max_size=5))
@example([("GPGST", ["120000.00", "1", "1", "1", "0", "1e200", "1e200", "1"], None),  # sigma² overflowed: a crash
          ("GPGGA", ["120000.00", "5800.0000", "N", "01500.0000", "E", "1", "08", "0.9", "100.0", "M", "25.0", "M", "", ""],
           (58.0, 15.0))], [])
@example([("GPGGA", ["120000.00", "0000.0000", "N", "18000.0001", "E", "1", "", "1e308", "1e308", "M", "", "M", "", ""],
           (0.0, 180.0 + 1e-4 / 60))], [])  # longitude beyond 180°, infinite sigmas
def test_nmea_sentences_with_any_field_values_give_plausible_fixes_or_counted_skips(sentences: list, sizes: list) -> None:
    """Checksum-valid sentences whose fields hold anything: each GGA ends as exactly one fix or
    one counted skip, and a fix is in range and at the position its GGA spelled out."""
    stream = b"".join(nmea_sentence(kind, fields) for kind, fields, _ in sentences)
    readings, gps = nmea_readings(stream, sizes)
    n_gga = sum(kind == "GPGGA" for kind, _, _ in sentences)
    outcomes = ("fixes", "no_fix", "implausible", "no_accuracy", "malformed")
    assert sum(gps.counts[k] for k in outcomes) == n_gga, dict(gps.counts)
    assert gps.counts["lines"] == len(sentences) == sum(gps.sentence_types.values())
    spelled = [angles for kind, _, angles in sentences if kind == "GPGGA"]
    for r in readings:
        assert_plausible_fix(r)
        assert any(abs(abs(r.lat_deg) - lat) < 1e-9 and abs(abs(r.lon_deg) - lon) < 1e-9 for lat, lon in spelled)


NMEA_NOISE = st.lists(st.sampled_from(list(b"$*,.\r\n\x000123456789ABCDEFGPNSWM")) | st.integers(0, 255),
                      max_size=100).map(bytes)


@fuzz(200)
@given(st.lists(NMEA_NOISE | NMEA_ANY.map(lambda s: nmea_sentence(s[0], s[1])), max_size=12),
       st.lists(st.integers(1, 90), max_size=5))
def test_nmea_driver_survives_any_bytes(pieces: list[bytes], sizes: list[int]) -> None:
    readings, gps = nmea_readings(b"".join(pieces), sizes)
    for r in readings:
        assert_plausible_fix(r)
    assert_lines_accounted(gps)


@st.composite
def nmea_epochs(draw: st.DrawFn) -> list[dict]:
    """Receiver epochs 0.2 s apart at distinct positions (exact in the sentences' 1e-7 arc-minutes)."""
    n = draw(st.integers(1, 7))
    lats = draw(st.lists(st.integers(0, 90 * 60 * 10**7), min_size=n, max_size=n, unique=True))
    return [{"lat_units": lat, "north": draw(st.booleans()), "lon_units": draw(st.integers(0, 180 * 60 * 10**7)),
             "east": draw(st.booleans()), "msl_mm": draw(st.integers(-10**6, 10**7)),
             "sigma_h_mm": draw(st.integers(1, 10**5)), "sigma_v_mm": draw(st.integers(1, 10**5)),
             "quality": draw(st.sampled_from([1, 1, 2, 0]))} for lat in lats]


def degrees_minutes(units: int, degree_digits: int) -> str:
    """``(d)ddmm.mmmmmmm`` for an angle in units of 1e-7 arc-minutes."""
    minutes, fraction = divmod(units, 10**7)
    return f"{minutes // 60:0{degree_digits}d}{minutes % 60:02d}.{fraction:07d}"


def epoch_sentences(i: int, e: dict) -> list[tuple[str, bytes]]:
    """RMC, GGA, GSA and (with a fix) GST of epoch ``i``, as a receiver sends them."""
    hms = f"1200{i * 20 // 100:02d}.{i * 20 % 100:02d}"
    fix = e["quality"] > 0
    position = [degrees_minutes(e["lat_units"], 2), "N" if e["north"] else "S",
                degrees_minutes(e["lon_units"], 3), "E" if e["east"] else "W"] if fix else ["", "", "", ""]
    h, s_h, s_v = e["msl_mm"] / 1000, e["sigma_h_mm"] / 1000, e["sigma_v_mm"] / 1000
    out = [("RMC", nmea_sentence("GPRMC", [hms, "A" if fix else "V", *position, "0.00", "", "010524", "", "", "A"])),
           ("GGA", nmea_sentence("GPGGA", [hms, *position, str(e["quality"]), "09", "0.9", f"{h:.3f}" if fix else "",
                                           "M", "25.000", "M", "", ""])),
           ("GSA", nmea_sentence("GPGSA", ["A", "3", *["07"] * 12, "1.7", "0.9", "1.4"]))]
    if fix:
        out.append(("GST", nmea_sentence("GPGST", [hms, f"{s_h:.3f}", f"{s_h:.3f}", f"{s_h:.3f}", "0.0", f"{s_h:.3f}",
                                                   f"{s_h:.3f}", f"{s_v:.3f}"])))
    return out


LINE_DAMAGE = st.one_of(
    st.tuples(st.just("replace"), st.integers(0, 999), st.integers(1, 255)),
    st.tuples(st.just("delete"), st.integers(0, 999)),
    st.tuples(st.just("insert"), st.integers(0, 999), st.integers(0, 255)),
    st.tuples(st.just("cut"), st.integers(0, 999), st.booleans()),    # cut off, with or without its line end
    st.tuples(st.just("checksum"), st.integers(1, 255)),
    st.tuples(st.just("noise"), st.binary(min_size=1, max_size=30)),  # bytes before an intact line
)


def damage(line: bytes, how: tuple) -> bytes:
    """``line`` (``$body*hh\\r\\n``) with one corruption; the body edits always break the checksum
    or the framing, except inserting a NUL (XOR-neutral), which cannot change a value either."""
    star = line.rindex(b"*")
    kind, pos = how[0], 1 + how[1] % (star - 1) if how[0] in ("replace", "delete", "insert") else 0
    if kind == "replace":
        return line[:pos] + bytes([(line[pos] + how[2]) % 256]) + line[pos + 1:]
    if kind == "delete":
        return line[:pos] + line[pos + 1:]
    if kind == "insert":
        return line[:pos] + bytes([how[2]]) + line[pos:]
    if kind == "cut":
        return line[:1 + how[1] % (len(line) - 3)] + (b"\r\n" if how[2] else b"")
    if kind == "checksum":
        return line[:star + 1] + f"{(int(line[star + 1:star + 3], 16) ^ how[1]):02X}".encode() + b"\r\n"
    return how[1] + line


@fuzz(150)
@given(nmea_epochs(), st.dictionaries(st.integers(0, 27), LINE_DAMAGE, max_size=8),
       st.lists(st.integers(1, 120), max_size=5))
@example([{"lat_units": 0, "north": False, "lon_units": 0, "east": False, "msl_mm": 0, "sigma_h_mm": 1, "sigma_v_mm": 1,
           "quality": 1}], {1: ("noise", b"\x80")}, [])  # a non-ASCII byte before a GGA lost the whole line
@example([{"lat_units": 0, "north": False, "lon_units": 0, "east": False, "msl_mm": 0, "sigma_h_mm": 1, "sigma_v_mm": 1,
           "quality": 1}] * 2, {1: ("insert", 212, 0)}, [])  # a NUL in the geoid separation passed as 0 m
def test_nmea_every_intact_epoch_survives_damaged_neighbours(epochs: list[dict], damages: dict, sizes: list) -> None:
    """A GGA line that arrives intact gives exactly its fix (position to the sentence's precision,
    sigmas from its epoch's GST or else from DOP); damaged lines give nothing invented, only
    counted skips."""
    stream, survived, k = bytearray(), {}, 0
    for i, e in enumerate(epochs):
        for kind, line in epoch_sentences(i, e):
            how = damages.get(k)
            sent = damage(line, how) if how else line
            start = len(stream) + (len(how[1]) if how and how[0] == "noise" else 0)
            stream += sent
            since_newline = start - (stream.rfind(b"\n", 0, start) + 1)
            survived[i, kind] = (how is None or how[0] == "noise") and since_newline + len(line) - 1 <= MAX_LINE
            k += 1
    readings, gps = nmea_readings(bytes(stream), sizes)

    def position(e: dict) -> tuple[float, float, float]:
        lat, lon = e["lat_units"] / 6e8, e["lon_units"] / 6e8
        return (lat if e["north"] else -lat, lon if e["east"] else -lon, e["msl_mm"] / 1000 + 25.0)

    expected = [i for i, e in enumerate(epochs) if e["quality"] > 0 and survived[i, "GGA"]]
    matched = []
    for r in readings:
        assert_plausible_fix(r)
        hits = [i for i, e in enumerate(epochs) if e["quality"] > 0 and np.allclose(
            (r.lat_deg, r.lon_deg, r.alt_m), position(e), rtol=0.0, atol=1e-9)]
        assert hits, f"a fix that no epoch sent: {r}"
        # Epochs drawn with the same position cannot be told apart: an intact one not yet matched first.
        i = min(hits, key=lambda h: (h in matched, h not in expected, h))
        e = epochs[i]
        if r.sigma_source == "GST":  # (a GST with a NUL inserted still passes its XOR checksum, unchanged)
            assert (r.fix.sigma_h, r.fix.sigma_v) == pytest.approx((e["sigma_h_mm"] / 1000, e["sigma_v_mm"] / 1000))
        else:
            assert r.sigma_source == "DOP" and r.fix.sigma_h == pytest.approx(0.9 * UERE_M / math.sqrt(2.0))
        matched.append(i)
    assert len(set(matched)) == len(matched), "an epoch gave two fixes"
    assert set(expected) <= set(matched), "an intact GGA gave no fix"
    assert_lines_accounted(gps)


# ================================================================================================
# MAVLink GPS_RAW_INT
# ================================================================================================
def uint(bits: int) -> st.SearchStrategy[int]:
    return st.integers(0, 2**bits - 1)


def sint(bits: int) -> st.SearchStrategy[int]:
    return st.integers(-(2 ** (bits - 1)), 2 ** (bits - 1) - 1)


GPS_RAW_INT_FIELDS = {  # every field over its whole wire type, with the usual values more often
    "time_usec": st.sampled_from([0, 1_000_000, 1_200_000]) | uint(64), "fix_type": st.integers(0, 8) | uint(8),
    "lat": st.integers(-900_000_000, 900_000_000) | sint(32), "lon": st.integers(-1_800_000_000, 1_800_000_000) | sint(32),
    "alt": sint(32), "eph": st.sampled_from([0, 90, 65535]) | uint(16), "epv": st.sampled_from([0, 140, 65535]) | uint(16),
    "vel": uint(16), "cog": uint(16), "satellites_visible": uint(8), "alt_ellipsoid": st.just(0) | sint(32),
    "h_acc": st.just(0) | uint(32), "v_acc": st.just(0) | uint(32), "vel_acc": uint(32), "hdg_acc": uint(32),
    "yaw": uint(16),
}
GPS_RAW_INT = st.fixed_dictionaries(GPS_RAW_INT_FIELDS)


@fuzz(200)
@given(st.lists(st.tuples(st.sampled_from([1, 1, 2]), GPS_RAW_INT), min_size=1, max_size=8))
@example([(1, {**dict.fromkeys(GPS_RAW_INT_FIELDS, 0), "fix_type": 3, "lat": 950_000_000, "eph": 90})])  # lat 95°
def test_mavlink_gps_raw_int_with_any_field_values_gives_plausible_fixes_or_counted_skips(messages: list) -> None:
    """Messages packed and parsed as on the wire; each ends as one fix or one counted skip."""
    gps = MavlinkGps(MavlinkGpsConfig("udpin:127.0.0.1:0", uere_m=UERE_M, system_id=1))
    receiver = mavutil.mavlink.MAVLink(None)
    readings = []
    for k, (system, fields) in enumerate(messages):
        sender = mavutil.mavlink.MAVLink(None, srcSystem=system, srcComponent=1)
        for msg in receiver.parse_buffer(sender.gps_raw_int_encode(**fields).pack(sender)) or []:
            reading = gps.convert(msg, 1_000_000_000 + k)
            if reading is not None:
                assert_plausible_fix(reading)
                assert (reading.lat_deg, reading.lon_deg) == (fields["lat"] * 1e-7, fields["lon"] * 1e-7)
                readings.append(reading)
    assert gps.counts["other_system"] == sum(system != 1 for system, _ in messages)
    skips = ("no_fix", "duplicate", "no_accuracy", "implausible")
    received = len(messages) - gps.counts["other_system"]
    assert gps.counts["messages"] == len(readings) + sum(gps.counts[k] for k in skips) == received
    assert gps.counts["fixes"] == len(readings)


# ================================================================================================
# Dataset CSV rows: times, numeric tables, the camera frame index, GPS rows
# ================================================================================================
TIME_TEXT = st.one_of(
    st.text(max_size=30),
    st.from_regex(r"\s*[-+]?\d{0,22}(\.\d{0,12})?([eE][-+]?\d{1,3})?\s*", fullmatch=True),
    st.sampled_from(["nan", "inf", "-Infinity", "sNaN", "1e999999999", "1E+99999999999999999999", "²", "٣", "1_000"]),
)


PARSE_TIME_ERRORS = ("not a number", "not finite", "time out of int64 range", "not an integer nanosecond time")


@fuzz(300)
@given(TIME_TEXT, st.sampled_from([1, 1000, 1_000_000_000]))
@example("²", 1)  # str.isdigit() but not int(): Python's message instead of ours
@example("1E+99999999999999999999", 1_000_000_000)  # beyond decimal's own exponent range
def test_parse_time_ns_gives_the_exact_int64_or_a_value_error_quoting_the_text(text: str, unit_ns: int) -> None:
    try:
        t = parse_time_ns(text, unit_ns)
    except ValueError as exc:  # the module's own message, quoting the text
        assert str(exc).split(": ")[0] in PARSE_TIME_ERRORS and str(exc).endswith(repr(text.strip())), str(exc)
        return
    assert type(t) is int and -(2**63) < t < 2**63
    assert t == int((Decimal(text.strip()) * unit_ns).to_integral_value())


@fuzz(200)
@given(st.integers(-(2**63) + 1, 2**63 - 1))
def test_times_round_trip_in_every_written_form(t: int) -> None:
    assert parse_time_ns(f" {t}\t") == t
    assert parse_time_ns(format(Decimal(t), "E")) == t  # 1.40363657975856E+18: EuRoC's spreadsheet form
    assert parse_time_ns(seconds_text(t), 1_000_000_000) == t


CSV_FIELD = st.sampled_from(["1", "2.5", "-3e2", "nan", "inf", "", "x", " 7 ", "1e400", "12345678901234567890", "0x1F",
                             "1.5e-3", "-0", "1e19", "٣"])
CSV_LINE = st.one_of(st.text(max_size=30), st.lists(CSV_FIELD, max_size=8).map(",".join),
                     st.lists(CSV_FIELD, max_size=8).map(" ".join), st.just("# a comment"), st.just(""))


def data_lines(path: Path) -> list[str]:
    """The lines of ``path`` that are not ``#`` comments (the column header is one)."""
    lines = path.read_text(encoding="utf-8-sig", errors="replace").splitlines()
    return [ln for ln in lines if not ln.strip().startswith("#")]


@fuzz(200)
@given(st.lists(CSV_LINE, max_size=12), st.integers(1, 4), st.sampled_from([",", None]), st.booleans())
def test_numeric_csv_takes_any_text_and_counts_every_line(scratch: Path, lines: list[str], n_values: int,
                                                          delimiter: str | None, header: bool) -> None:
    path = scratch / "table.csv"
    head = "#" + (delimiter or " ").join(["t"] + ["v"] * n_values)
    path.write_text("\n".join(([head] if header else []) + lines), encoding="utf-8", errors="surrogatepass")
    try:
        data = read_numeric_csv(path, n_values, delimiter=delimiter, require_header=delimiter == ",")
    except ValueError as exc:
        assert str(path) in str(exc) and "header" in str(exc)
        return
    assert len(data.t_ns) + data.skipped == len(data_lines(path))
    assert data.values.shape == (len(data.t_ns), n_values) and np.all(np.isfinite(data.values))
    assert np.all(np.diff(data.t_ns) > 0)


JUNK_TOKEN = st.sampled_from(["", "x", "1.2.3", "--1", "0x10", "1e", "one", "nan", "inf", "-inf", "1e999"])


@st.composite
def table_with_junk(draw: st.DrawFn) -> tuple[int, str | None, list[int], list[list[float]], list[str], int]:
    """Good rows (strictly later times, any finite values) with junk lines that can never be a
    valid later row: wrong field counts, non-numbers, non-finite values, times that do not advance."""
    n_values, delimiter = draw(st.integers(1, 5)), draw(st.sampled_from([",", None]))
    sep = delimiter or draw(st.sampled_from([" ", "\t", "  "]))
    times = np.cumsum(draw(st.lists(st.integers(1, 10**12), min_size=1, max_size=10))) + draw(st.integers(-(10**15), 10**15))
    rows = [draw(st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=n_values, max_size=n_values))
            for _ in times]
    lines, junk = [], 0
    for k, (t, row) in enumerate(zip(times.tolist(), rows)):
        for _ in range(draw(st.integers(0, 2))):
            fields = [str(t)] + [repr(v) for v in row]
            kind = draw(st.sampled_from(["count", "token", "blank", "comment", "fraction"] + (["late"] if k else [])))
            if kind == "late":
                fields[0] = str(draw(st.integers(times[k - 1] - 10**6, times[k - 1])))
            elif kind == "count":
                fields = fields[:-1] if draw(st.booleans()) else fields + ["1"]
            elif kind == "token":
                fields[draw(st.integers(1, n_values))] = draw(JUNK_TOKEN)
            elif kind == "fraction":
                fields[0] += ".5"
            line = {"blank": "", "comment": "# " + sep.join(fields)}.get(kind, sep.join(fields))
            lines.append(line)
            junk += kind != "comment"
        lines.append(sep.join([str(t)] + [repr(v) for v in row]))
    return n_values, delimiter, times.tolist(), rows, lines, junk


@fuzz(200)
@given(table_with_junk())
def test_numeric_csv_keeps_every_good_row_exactly_and_counts_the_junk(scratch: Path, case: tuple) -> None:
    n_values, delimiter, times, rows, lines, junk = case
    path = scratch / "rows.csv"
    path.write_text("\n".join(["#" + (delimiter or " ").join(["t"] + ["v"] * n_values), *lines]) + "\n", encoding="utf-8")
    data = read_numeric_csv(path, n_values, delimiter=delimiter)
    assert data.t_ns.tolist() == times
    assert data.values.tolist() == rows
    assert data.skipped == junk


@fuzz(200)
@given(st.lists(st.one_of(st.text(max_size=30), st.tuples(st.integers(-5, 10**19), st.sampled_from(
    ["a.png", "sub/b.png", "../up.png", "/abs.png", "", "c.png,extra"])).map(lambda r: f"{r[0]},{r[1]}")), max_size=12))
def test_frame_index_takes_any_text_and_counts_every_line(scratch: Path, lines: list[str]) -> None:
    path, images = scratch / "cam.csv", scratch / "images"
    path.write_text("\n".join(lines), encoding="utf-8", errors="surrogatepass")
    frames, skipped = read_frame_index(path, images)
    meaningful = [ln for ln in data_lines(path) if ln.strip()]
    assert len(frames) + skipped == len(meaningful)
    assert all(p.resolve().is_relative_to(images.resolve()) for _, p in frames), "an image path left the folder"
    assert all(b[0] > a[0] for a, b in zip(frames, frames[1:]))


GOOD_FIX = st.tuples(st.floats(-90.0, 90.0), st.floats(-180.0, 180.0), st.floats(-500.0, 9000.0),
                     st.floats(0.01, 100.0), st.floats(0.01, 100.0))
ANY_FIX = st.tuples(*[st.floats(allow_nan=False, allow_infinity=False)] * 5)


@fuzz(60)
@given(st.lists(st.tuples(st.booleans(), GOOD_FIX, ANY_FIX), min_size=1, max_size=10), st.booleans())
@example([(True, (58.0, 15.0, 90.0, 1.0, 2.0), ()), (False, (), (95.0, 15.0, 90.0, 1.0, 2.0))], True)  # lat 95°
@example([(False, (), (10.0, 10.0, 1e308, 1.0, 1.0)), (True, (58.0, 15.0, 90.0, 1.0, 2.0), ())], False)  # a useless origin
def test_dataset_gps_rows_become_finite_fixes_or_counted_skips(scratch: Path, rows: list, with_origin: bool) -> None:
    """WGS84 rows of any finite values: off the globe or without a positive sigma is a counted skip."""
    root = scratch / "gps-dataset"
    writer = DatasetWriter(root)
    origin = (58.4, 15.6, 100.0) if with_origin else None
    writer.write_calibration(Calibration(ImuCalibration(100.0, ImuNoise.isotropic(1e-4, 1e-5, 1e-3, 1e-4)),
                                         GpsCalibration(origin_lla=origin)), "fuzz", "property test")
    chosen = [good if is_good else other for is_good, good, other in rows]
    lines = [f"{1_000_000_000 * (k + 1)},{','.join(repr(v) for v in fix)}" for k, fix in enumerate(chosen)]
    (root / "mav0/gps0").mkdir(parents=True, exist_ok=True)
    (root / "mav0/gps0/data.csv").write_text("#timestamp [ns],lat [deg],lon [deg],alt [m],sigma_h [m],sigma_v [m]\n"
                                             + "\n".join(lines) + "\n")
    (root / "mav0/gps0/sensor.yaml").write_text("frame: WGS84\n")
    dataset = Dataset.open(root)

    def usable(fix: tuple) -> bool:
        lat, lon, alt, sigma_h, sigma_v = fix
        return abs(lat) <= 90 and abs(lon) <= 180 and abs(alt) <= 1e5 and sigma_h > 0 and sigma_v > 0

    if not any(usable(fix) for fix in chosen):
        with pytest.raises(ValueError, match="gps0/data.csv: no usable fix"):
            dataset.gps()
        return
    gps = dataset.gps()
    assert gps.t_ns.tolist() == [1_000_000_000 * (k + 1) for k, fix in enumerate(chosen) if usable(fix)]
    assert np.all(np.isfinite(gps.p_ned)) and np.all(gps.sigma_h > 0) and np.all(gps.sigma_v > 0)
    assert dataset.skipped["mav0/gps0/data.csv"] == len(chosen) - len(gps.t_ns)


# ================================================================================================
# Trajectories (TUM, EuRoC CSV)
# ================================================================================================
TRAJECTORY_LINE = st.one_of(st.binary(max_size=40), st.just(b"1.0 0 0 0 0 0 0 1"),
                            st.lists(CSV_FIELD, min_size=1, max_size=17).flatmap(
                                lambda f: st.sampled_from([" ", ","]).map(lambda sep: sep.join(f).encode())))
TRAJECTORY_HEAD = st.sampled_from([b"", b"#t,x,y,z\n", b"#" + b",".join([b"c"] * 17) + b"\n", b"# t x y z qx qy qz qw\n"])


@fuzz(200)
@given(st.lists(TRAJECTORY_LINE, max_size=10), TRAJECTORY_HEAD)
def test_read_tum_takes_any_bytes(scratch: Path, lines: list[bytes], head: bytes) -> None:
    """TUM, 17-column EuRoC truth or 4-column positions (told by the first line): trajectory or ValueError."""
    path = scratch / "traj.txt"
    path.write_bytes(head + b"\n".join(lines))
    try:
        t, p, q = read_tum(path)
    except ValueError as exc:
        assert str(path) in str(exc)
        return
    assert np.all(np.diff(t) > 0) and np.all(np.isfinite(p))
    assert q is None or np.allclose(np.linalg.norm(q, axis=1), 1.0)


UNIT_QUATERNION = st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).map(
    lambda q: np.asarray(q) / np.linalg.norm(q) if np.linalg.norm(q) > 0.1 else np.array([1.0, 0.0, 0.0, 0.0]))


TUM_JUNK = st.sampled_from(["", "# note", "1 2 3", "x y z 1 2 3 4 5", "5 0 0 0 0 0 0 nan"])


@fuzz(100)
@given(st.lists(st.tuples(st.integers(1, 10**12), st.lists(st.floats(-1e5, 1e5), min_size=3, max_size=3), UNIT_QUATERNION),
                min_size=1, max_size=8), st.lists(TUM_JUNK, max_size=4))
def test_tum_round_trips_with_junk_lines_between(scratch: Path, poses: list, junk: list[str]) -> None:
    t = np.cumsum([dt for dt, _, _ in poses]).astype(np.int64)
    p, q = np.array([x for _, x, _ in poses]), np.array([x for _, _, x in poses])
    path = scratch / "round.txt"
    write_tum(path, t, p, q)
    lines = path.read_text().splitlines()
    for k, extra in enumerate(junk):  # junk after the header, between good lines
        lines.insert(1 + (k * 7) % len(lines), extra)
    path.write_text("\n".join(lines) + "\n")
    t2, p2, q2 = read_tum(path)
    assert t2.tolist() == t.tolist()
    assert np.allclose(p2, p, rtol=0.0, atol=1e-9) and np.allclose(q2, q, rtol=0.0, atol=2e-9)


# ================================================================================================
# dataset.yaml calibration
# ================================================================================================
YAML_SCALAR = st.one_of(st.none(), st.booleans(), st.integers(), st.integers(-10, 10), st.floats(),
                        st.floats(0.0, 10.0), st.text(max_size=6))


def yaml_containers(inner: st.SearchStrategy) -> st.SearchStrategy:
    return st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)


YAML_VALUE = st.recursive(YAML_SCALAR, yaml_containers, max_leaves=12)
ROTATION = UNIT_QUATERNION.map(lambda q: quat_to_rot(q))
FINITE = st.floats(-1e6, 1e6)
NOISE = st.floats(0.0, 1.0) | st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3)


@st.composite
def calibrations(draw: st.DrawFn) -> Calibration:
    vec = st.lists(FINITE, min_size=3, max_size=3)
    camera = None
    if draw(st.booleans()):
        camera = CameraCalibration(draw(st.integers(1, 4000)), draw(st.integers(1, 4000)), draw(st.floats(1.0, 5000.0)),
                                   draw(st.floats(1.0, 5000.0)), draw(FINITE), draw(FINITE),
                                   draw(st.lists(st.floats(-1.0, 1.0), min_size=5, max_size=5)), draw(ROTATION), draw(vec),
                                   draw(st.floats(0.1, 100.0)), draw(st.floats(-1.0, 1.0)))
    origin = draw(st.none() | st.tuples(st.floats(-90.0, 90.0), st.floats(-180.0, 180.0), st.floats(-500.0, 9000.0)))
    return Calibration(
        ImuCalibration(draw(st.floats(1.0, 2000.0)), ImuNoise(*(np.broadcast_to(draw(NOISE), 3) for _ in range(4))),
                       draw(ROTATION), draw(st.floats(9.0, 10.0))),
        GpsCalibration(draw(vec), origin, draw(st.floats(-1.0, 1.0))), camera,
        draw(st.none() | st.floats(-math.pi, math.pi)), draw(st.none() | st.floats(1e-3, 1.0)), draw(vec),
        draw(st.none() | st.floats(1e-4, 1.0)))


def as_dataset_yaml(cal: Calibration) -> dict:
    """What ``DatasetWriter`` writes, through YAML text and back, as a reader would see it."""
    doc = {"format": "vtolpose-dataset/1", "name": "fuzz", "description": "", **calibration_to_yaml(cal)}
    return yaml.safe_load(yaml.safe_dump(doc, sort_keys=False))


def paths_in(doc: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key path of a YAML tree (list items as int steps)."""
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    return [p for key, value in items for p in [(*prefix, key), *paths_in(value, (*prefix, key))]]


def assert_close_trees(a: Any, b: Any) -> None:
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for key in a:
            assert_close_trees(a[key], b[key])
    elif isinstance(a, list):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            assert_close_trees(x, y)
    elif isinstance(a, float):
        assert b == pytest.approx(a, rel=1e-12, abs=1e-300)  # headings pass through degrees and back
    else:
        assert a == b


@fuzz(150)
@given(calibrations())
def test_calibration_yaml_round_trips(cal: Calibration) -> None:
    assert_close_trees(calibration_to_yaml(calibration_from_yaml(as_dataset_yaml(cal), "d.yaml")), calibration_to_yaml(cal))


@fuzz(200)
@given(YAML_VALUE)
def test_calibration_from_any_yaml_document_is_a_calibration_or_names_the_file(doc: Any) -> None:
    try:
        calibration_from_yaml(doc, "fuzz/dataset.yaml")
    except CalibrationError as exc:
        assert str(exc).startswith("fuzz/dataset.yaml: ")


@fuzz(150)
@given(calibrations(), st.data())
def test_a_corrupted_calibration_value_is_an_error_naming_its_key(cal: Calibration, data: st.DataObject) -> None:
    doc = as_dataset_yaml(cal)
    path = data.draw(st.sampled_from(paths_in(doc)))
    parent = doc
    for step in path[:-1]:
        parent = parent[step]
    action = data.draw(st.sampled_from(["set", "delete", "add"] if isinstance(parent, dict) else ["set"]))
    if action == "set":
        parent[path[-1]] = data.draw(YAML_VALUE)
    elif action == "delete":
        del parent[path[-1]]
    else:
        path = (*path[:-1], data.draw(st.text(min_size=1, max_size=8)))
        assume(path[-1] not in parent)
        parent[path[-1]] = data.draw(YAML_VALUE)
    try:
        calibration_from_yaml(doc, "d.yaml")
    except CalibrationError as exc:
        keys = [k for k in path if isinstance(k, str)]
        named = [".".join(keys[:n]) for n in range(1, len(keys) + 1)]
        assert any(name in str(exc) for name in named) or "unknown key" in str(exc), (path, str(exc))


@fuzz(100)
@given(st.binary(max_size=60) | YAML_VALUE.map(lambda d: yaml.safe_dump(d).encode()))
@example(b"format: vtolpose-dataset/1\nimu: " + b"[" * 1000)  # RecursionError
@example(b"format: vtolpose-dataset/1\n\x80")  # UnicodeDecodeError
def test_dataset_open_reads_any_dataset_yaml_or_names_it(scratch: Path, text: bytes) -> None:
    root = scratch / "yaml-dataset"
    root.mkdir(exist_ok=True)
    (root / "dataset.yaml").write_bytes(text)
    try:
        Dataset.open(root)
    except CalibrationError as exc:
        assert str(exc).startswith(str(root / "dataset.yaml"))


# ================================================================================================
# Configuration
# ================================================================================================
DEFAULTS = config.default_config()
SECTIONS = sorted({k.rsplit(".", n)[0] for k in SCHEMA for n in range(1, k.count(".") + 1)})


def valid_value(field: Any) -> st.SearchStrategy:
    """Values the schema accepts for ``field`` (the loader's success path needs plenty of these)."""
    if field.choices:
        return st.sampled_from(field.choices)
    low = field.minimum if field.minimum is not None else 0.0 if field.positive else -1e6
    high = field.maximum if field.maximum is not None else 1e6
    kinds = {
        "bool": st.booleans(), "str": st.text(min_size=1, max_size=8),
        "list": st.lists(st.sampled_from(field.items or ("x",))),
        "int": st.integers(math.ceil(low) + (field.positive and low <= 0), math.floor(high)),
        "float": st.floats(low, high, exclude_min=field.positive and low <= 0),
        "vector3": st.lists(FINITE, min_size=3, max_size=3), "matrix3": ROTATION.map(lambda r: r.tolist()),
    }
    return kinds[field.kind] | (st.none() if field.nullable else st.nothing())


VALID_OVERRIDE = st.sampled_from(sorted(SCHEMA)).flatmap(lambda k: st.tuples(st.just(k), valid_value(SCHEMA[k])))
ANY_OVERRIDE = st.tuples(st.sampled_from(sorted(SCHEMA)) | st.sampled_from(SECTIONS)
                         | st.sampled_from(sorted(SCHEMA)).map(lambda k: k + "s") | st.text(min_size=1, max_size=10),
                         YAML_VALUE)
OVERRIDES = st.tuples(st.lists(VALID_OVERRIDE, max_size=4), st.lists(ANY_OVERRIDE, max_size=1)).map(lambda t: t[0] + t[1])


def nest(pairs: list[tuple[str, Any]]) -> dict:
    """A nested override tree from dotted keys (a later key replaces what was in its way)."""
    tree: dict = {}
    for dotted, value in pairs:
        node, (*parents, last) = tree, dotted.split(".")
        for part in parents:
            node[part] = node[part] if isinstance(node.get(part), dict) else {}
            node = node[part]
        node[last] = value
    return tree


def leaves(tree: dict, prefix: str = "") -> dict[str, Any]:
    """Dotted key -> value; a mapping under a known section is a section, anything else a value."""
    out = {}
    for key, value in tree.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict) and path in SECTIONS:
            out.update(leaves(value, path + "."))
        else:
            out[path] = value
    return out


def loaded(path: Path | None = None, overrides: dict | None = None) -> dict[str, Any] | ConfigError:
    """``load_config``'s result or its ConfigError (defaults parsed once: the tree is what varies)."""
    with mock.patch.object(config, "default_config", lambda: copy.deepcopy(DEFAULTS)):
        try:
            return load_config(path, overrides)
        except ConfigError as exc:
            return exc


@fuzz(120)
@given(OVERRIDES)
def test_config_overrides_load_or_fail_naming_the_key(scratch: Path, pairs: list) -> None:
    """Any override tree: either every value given comes back (floats as floats) or one ConfigError
    names the key at fault — and a YAML file with the same tree behaves the same."""
    tree = nest(pairs)
    result = loaded(overrides=tree)
    given_keys = leaves(tree)
    if isinstance(result, ConfigError):  # the override's own key (or section), or a cross-checked one
        own = {".".join(k.split(".")[:n]) for k in given_keys for n in range(1, k.count(".") + 2)}
        named = own if str(result).startswith("command line: ") else set(SCHEMA)
        assert any(f"key '{k}'" in str(result) for k in named), str(result)
    else:
        for key, value in given_keys.items():
            assert result[key] == value and type(result[key]) is (float if SCHEMA[key].kind == "float" and value is not None
                                                                  else type(value))
    path = scratch / "user.yaml"
    path.write_text(yaml.safe_dump(tree, allow_unicode=True, sort_keys=False), encoding="utf-8")
    from_file = loaded(path)
    if yaml.safe_load(path.read_text(encoding="utf-8")) != tree:  # PyYAML folds some characters ('\x85')
        result = loaded(overrides=yaml.safe_load(path.read_text(encoding="utf-8")))
    if isinstance(result, ConfigError):
        assert isinstance(from_file, ConfigError)
        assert str(from_file).split(": ", 1)[1] == str(result).split(": ", 1)[1]
    else:
        assert from_file == result


@fuzz(100)
@given(st.binary(max_size=80) | st.text(max_size=80).map(str.encode) | YAML_VALUE.map(lambda d: yaml.safe_dump(d).encode()))
@example(b"vehicle: " + b"[" * 1000)  # RecursionError
@example(b"\xff\xfe")  # UnicodeDecodeError
@example(b"vehicle: {name: !!binary aGk=}")
def test_config_file_with_any_bytes_loads_or_names_the_file(scratch: Path, data: bytes) -> None:
    path = scratch / "any.yaml"
    path.write_bytes(data)
    result = loaded(path)
    if isinstance(result, ConfigError):
        assert str(result).startswith(f"config file {path}: "), str(result)


# ================================================================================================
# --fault specs
# ================================================================================================
SPEC_TEXT = st.one_of(
    st.text(max_size=40),
    st.lists(st.sampled_from([*FAULT_KINDS, "imu", "gps", "camera", "0", "1.5", "-2", "nan", "inf", "1e309", "", "x",
                              "20,0,0", "1,2", "0.5", "1_0", " 3 "]), min_size=1, max_size=6).map(":".join),
)


@fuzz(300)
@given(SPEC_TEXT)
def test_fault_spec_parses_or_names_the_spec(spec: str) -> None:
    try:
        fault = parse_fault(spec)
    except FaultError as exc:
        assert str(exc).startswith("--fault ")
        return
    assert fault.kind in FAULT_KINDS and fault.spec == spec.strip()
    assert 0.0 <= fault.start_s < math.inf and fault.duration_s > 0.0
    assert fault.kind != "clock-step" or 0.0 < abs(fault.step_s) <= MAX_CLOCK_STEP_S
    assert fault.kind != "gps-multipath" or (fault.sigma_m > 0.0 and 0.0 < fault.rate <= 1.0)


POSITIVE = st.floats(1e-3, 1e4)
VALID_SPEC = st.one_of(
    st.tuples(st.sampled_from(["gps-off", "camera-off", "imu-gap", "camera-freeze"]), st.floats(0.0, 1e4), POSITIVE).map(
        lambda a: (f"{a[0]}:{a[1]!r}:{a[2]!r}", {"kind": a[0], "start_s": a[1], "duration_s": a[2]})),
    st.tuples(st.floats(0.0, 1e4), st.lists(FINITE, min_size=3, max_size=3), POSITIVE).map(
        lambda a: (f"gps-jump:{a[0]!r}:{','.join(map(repr, a[1]))}:{a[2]!r}",
                   {"kind": "gps-jump", "start_s": a[0], "offset_m": tuple(a[1]), "duration_s": a[2]})),
    st.tuples(st.floats(0.0, 1e4), POSITIVE, POSITIVE, st.floats(1e-3, 1.0)).map(
        lambda a: (f"gps-multipath:{a[0]!r}:{a[1]!r}:{a[2]!r}:{a[3]!r}",
                   {"kind": "gps-multipath", "start_s": a[0], "duration_s": a[1], "sigma_m": a[2], "rate": a[3]})),
    st.tuples(st.floats(0.0, 1e4), st.floats(-MAX_CLOCK_STEP_S, MAX_CLOCK_STEP_S).filter(bool)).map(
        lambda a: (f"clock-step:{a[0]!r}:{a[1]:+}", {"kind": "clock-step", "start_s": a[0], "step_s": a[1]})),
    st.tuples(st.sampled_from(["imu", "gps"]), st.floats(0.0, 1e4), POSITIVE).map(
        lambda a: (f"nan:{a[0]}:{a[1]!r}:{a[2]!r}", {"kind": "nan", "sensor": a[0], "start_s": a[1], "duration_s": a[2]})),
)


@fuzz(200)
@given(st.lists(VALID_SPEC, max_size=4))
def test_valid_fault_specs_round_trip_and_at_most_one_clock_step(specs: list) -> None:
    texts = [text for text, _ in specs]
    if sum(expected["kind"] == "clock-step" for _, expected in specs) > 1:
        with pytest.raises(FaultError, match="at most one clock-step"):
            parse_faults(texts)
        return
    for fault, (text, expected) in zip(parse_faults(texts), specs, strict=True):
        assert fault.spec == text
        assert {key: getattr(fault, key) for key in expected} == expected
