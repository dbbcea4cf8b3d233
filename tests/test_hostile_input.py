"""Damaged and hostile input: YAML alias bombs, image bombs, implausible IMU readings, a full
disk, recording on replay, and configuration errors that blame the right source."""

import logging
import shutil
import struct
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from vtolpose.config import ConfigError, load_config
from vtolpose.config.yaml_limits import MAX_NODES, UnsafeYaml, load_bounded
from vtolpose.drivers.files.calibration_yaml import CalibrationError
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.files.frames_csv import image_size, load_grey
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.estimator.core.rotation import rotation_angle
from vtolpose.service.cli import main
from vtolpose.service.replay.session import replay


def laughs(levels: int = 9, width: int = 10) -> str:
    """A billion-laughs document: ``width ** levels`` values in a few hundred bytes."""
    lines = [f"a0: &a0 [{', '.join(['lol'] * width)}]"]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * width)}]" for i in range(1, levels + 1)]
    return "\n".join(lines) + f"\nbomb: *a{levels}\n"


@pytest.fixture(scope="module")
def flight_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("hostile") / "landfill"
    write_flight(simulate_flight("landfill", 40.0, 2), root)
    return root


def damaged_copy(src: Path, dst: Path, rows: dict[int, dict[int, str]]) -> Path:
    """A copy of the dataset with IMU data rows changed: ``{row: {column: text}}`` (row 0: the first data row)."""
    shutil.copytree(src, dst)
    path = dst / "mav0/imu0/data.csv"
    lines = path.read_text().splitlines()
    for row, changes in rows.items():
        fields = lines[row + 1].split(",")
        for column, text in changes.items():
            fields[column] = text
        lines[row + 1] = ",".join(fields)
    path.write_text("\n".join(lines) + "\n")
    return dst


# ----------------------------------------------------------------------------------- YAML
def test_alias_bombs_are_refused_before_they_are_built(tmp_path, flight_dir):
    with pytest.raises(UnsafeYaml, match=f"more than {MAX_NODES} values"):
        load_bounded(laughs())
    with pytest.raises(UnsafeYaml, match="refers to the node that contains it"):
        load_bounded("a: &a [1, *a]")
    assert load_bounded("base: &b {x: 1}\nuse: *b\n") == {"base": {"x": 1}, "use": {"x": 1}}  # small aliases are fine

    data = shutil.copytree(flight_dir, tmp_path / "ds")
    (data / "dataset.yaml").write_text("format: vtolpose-dataset/1\n" + laughs())
    started = time.monotonic()
    with pytest.raises(CalibrationError, match="dataset.yaml: its aliases expand to more than"):
        Dataset.open(data)
    config = tmp_path / "vehicle.yaml"
    config.write_text(laughs())
    with pytest.raises(ConfigError, match=f"config file {config}: its aliases expand"):
        load_config(config)
    assert main(["run", "--replay", str(flight_dir), "--set", f"vehicle.name={laughs().replace(chr(10), ' ')}"]) == 2
    assert time.monotonic() - started < 30  # refused, not expanded (it would take gigabytes)


def test_a_huge_configuration_file_is_not_read(tmp_path):
    config = tmp_path / "vehicle.yaml"
    config.write_text("# padding\n" * 200_000)
    with pytest.raises(ConfigError, match="larger than 1024 kB"):
        load_config(config)


# --------------------------------------------------------------------------------- images
def png_header_bomb(path: Path, side: int = 20000) -> None:
    """A valid PNG of side × side black pixels: about 400 kB on disk, 400 MB decoded."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    rows = zlib.compressobj(9)
    body = b"".join(rows.compress(b"\0" * (side + 1)) for _ in range(side)) + rows.flush()
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0))
                     + chunk(b"IDAT", body) + chunk(b"IEND", b""))


def test_image_sizes_are_read_from_the_header_before_decoding(tmp_path, caplog):
    for ext in ("png", "jpg", "bmp", "pgm"):
        cv2.imwrite(str(tmp_path / f"small.{ext}"), np.zeros((37, 53), np.uint8))
        assert image_size(tmp_path / f"small.{ext}") == (53, 37), ext
    bomb = tmp_path / "bomb.png"
    png_header_bomb(bomb)
    assert bomb.stat().st_size < 1_000_000 and image_size(bomb) == (20000, 20000)
    with caplog.at_level(logging.WARNING):
        assert load_grey(bomb) is None
    assert "20000 x 20000 pixels by its header" in caplog.text and "not decoded" in caplog.text
    (tmp_path / "text.png").write_text("not an image")
    assert load_grey(tmp_path / "text.png") is None
    assert load_grey(tmp_path / "small.png").shape == (37, 53)


# ----------------------------------------------------------------------------- IMU plausibility
def attitude_errors_deg(result, flight_dir: Path) -> np.ndarray:
    truth = Dataset.open(flight_dir).truth()
    k = np.searchsorted(truth.t_ns, result.trajectory.t_ns).clip(0, len(truth.t_ns) - 1)
    return np.degrees(rotation_angle(result.trajectory.q, truth.q[k]))


def test_readings_beyond_the_imu_range_are_refused_and_counted(flight_dir, tmp_path):
    cfg = load_config()
    clean = replay(Dataset.open(flight_dir), cfg)
    n = len(Dataset.open(flight_dir).imu().t_ns)
    damaged = damaged_copy(flight_dir, tmp_path / "damaged", {n // 2: {3: "100.0"}, n // 2 + 300: {3: "1e30"},
                                                              n // 2 + 600: {6: "-400.0"}})
    result = replay(Dataset.open(damaged), cfg)
    imu = result.estimator.counts_report()["imu"]
    assert imu["rejected"] == {"out_of_range": 3} and imu["received"] == n
    assert result.trajectory.t_ns.size == clean.trajectory.t_ns.size
    # The attitude never notices: the same to a hundredth of a degree as without the damage.
    assert np.max(np.abs(attitude_errors_deg(result, flight_dir) - attitude_errors_deg(clean, flight_dir))) < 0.01


def test_a_reset_after_a_corrupted_attitude_restores_the_attitude(tmp_path):
    """A reading inside the range but wrong (30 rad/s, once) turns the attitude; the GPS fixes are then
    refused, and the reset after that levels the attitude again (before: every later reset kept it, 78 m off)."""
    root = tmp_path / "landfill"
    flight = simulate_flight("landfill", 120.0, 1)
    write_flight(flight, root)
    n = len(flight.imu.t_ns)
    damaged = damaged_copy(root, tmp_path / "turned", {n // 2: {1: "20.0", 3: "30.0"}})
    result = replay(Dataset.open(damaged), load_config())
    events = " ".join(e.message for e in result.estimator.events)
    assert "attitude levelled again" in events and "heading placed" in events
    truth = Dataset.open(root).truth()
    k = min(np.searchsorted(truth.t_ns, result.trajectory.t_ns[-1]), len(truth.t_ns) - 1)
    assert np.linalg.norm(result.trajectory.p[-1] - truth.p[k]) < 10.0


# --------------------------------------------------------------------------- files and run
@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (a device whose writes fail: disk full)")
def test_a_full_disk_still_ends_a_clean_stop_and_fails_the_command(flight_dir, capsys):
    """The poses flow to the end, and the command fails: a script or a service manager must not take an
    incomplete trajectory for success. The reason is the last line."""
    assert main(["run", "--replay", str(flight_dir), "--out", "/dev/full"]) == 1
    out = capsys.readouterr().out
    assert "stopped by end of data" in out
    assert out.splitlines()[-1] == "the trajectory file /dev/full is incomplete: No space left on device"
    assert main(["replay", str(flight_dir), "--no-progress", "--out", "/dev/full"]) == 1
    assert capsys.readouterr().out.splitlines()[-1] == "the trajectory /dev/full is incomplete: No space left on device"


def test_recording_on_replay_is_refused_or_said(flight_dir, tmp_path, capsys, caplog):
    assert main(["run", "--replay", str(flight_dir), "--record", str(tmp_path / "rec")]) == 2
    assert "--record writes what live sensors deliver" in capsys.readouterr().err
    config = tmp_path / "vehicle.yaml"
    config.write_text(f"run:\n  record_dir: {tmp_path / 'flights'}\n")
    with caplog.at_level(logging.WARNING):
        assert main(["run", "--replay", str(flight_dir), "--config", str(config)]) == 0
    assert "run.record_dir" in caplog.text and "not used with --replay" in caplog.text
    assert not (tmp_path / "rec").exists() and not (tmp_path / "flights").exists()


def test_dataset_warnings_are_given_once(flight_dir, tmp_path, caplog):
    data = shutil.copytree(flight_dir, tmp_path / "ds")
    gps = data / "mav0/gps0/data.csv"
    lines = gps.read_text().splitlines()
    lines[40] = "garbage"
    fields = lines[50].split(",")
    fields[4] = "-1"
    lines[50] = ",".join(fields)
    gps.write_text("\n".join(lines) + "\n")
    with caplog.at_level(logging.WARNING):
        assert main(["replay", str(data), "--no-progress"]) == 0
    assert caplog.text.count("skipped 1 malformed line") == 1 and caplog.text.count("skipped 1 fix(es) with sigma") == 1


# ------------------------------------------------------------------------------ configuration
def test_checks_across_keys_blame_where_the_value_came_from(tmp_path):
    config = tmp_path / "vehicle.yaml"
    config.write_text("outputs:\n  mavlink:\n    require_signing: true\n")
    with pytest.raises(ConfigError, match=rf"^config file {config}: key 'outputs.mavlink.require_signing'"):
        load_config(config)
    with pytest.raises(ConfigError, match=r"^command line: key 'outputs.mavlink.endpoints\[0\]'"):
        load_config(None, {"outputs": {"mavlink": {"endpoints": ["x"]}}})  # an element of a list given there
    with pytest.raises(ConfigError, match=r"^command line: key 'outputs.mavlink.require_signing'"):
        load_config(None, {"outputs": {"mavlink": {"require_signing": True}}})
    with pytest.raises(ConfigError, match=r"^command line: key 'outputs.zenoh.listen': a client does not listen"):
        load_config(None, {"outputs": {"zenoh": {"mode": "client", "listen": ["tcp/127.0.0.1:7447"]}}})
    assert load_config(None, {"outputs": {"zenoh": {"mode": "client"}}})["outputs.zenoh.mode"] == "client"


def test_a_number_with_an_exponent_is_a_number_and_its_range_is_checked(tmp_path, capsys):
    with pytest.raises(ConfigError, match=r"key 'outputs.mavlink.rate_hz': must be at most 1000.0 \(got 1000000000000.0"):
        load_config(None, {"outputs": {"mavlink": {"rate_hz": "1e12"}}})
    assert main(["run", "--replay", "nowhere", "--set", "outputs.mavlink.rate_hz=1e12"]) == 2
    assert "must be at most 1000.0" in capsys.readouterr().err
    assert load_config(None, {"outputs": {"mavlink": {"rate_hz": "2.5e1"}}})["outputs.mavlink.rate_hz"] == 25.0


def test_tls_files_with_plain_endpoints_are_refused_or_warned(tmp_path, caplog):
    for name in ("ca.pem", "node.pem", "node.key"):
        (tmp_path / name).write_text("-")
    tls = {"root_ca_certificate": str(tmp_path / "ca.pem"), "certificate": str(tmp_path / "node.pem"),
           "private_key": str(tmp_path / "node.key")}
    with pytest.raises(ConfigError, match=r"command line: key 'outputs.zenoh.tls.root_ca_certificate': TLS is configured "
                                          r"but no endpoint is tls/ or quic/ \(tcp/127.0.0.1:7448\)"):
        load_config(None, {"outputs": {"zenoh": {"enabled": True, "tls": tls}}})
    with caplog.at_level(logging.WARNING):
        load_config(None, {"outputs": {"zenoh": {"enabled": True, "tls": tls, "connect": ["tls/localhost:7449"]}}})
    assert "tcp/127.0.0.1:7448 is plain text" in caplog.text
