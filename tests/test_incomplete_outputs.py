"""A requested file that could not be written in full fails the command: a full disk under the MCAP
recording of a replay, under the flight recording of a live run. The poses flow to the end all the
same; the exit code is non-zero and the last line says which file and why."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.service.cli import main

FULL = os.strerror(errno.ENOSPC)


@pytest.fixture(scope="module")
def flight_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("outputs") / "flight"
    write_flight(simulate_flight("landfill", 12.0, 5), root)
    return root


class FullDiskWriter:
    """The MCAP SDK's writer on a disk that fills up: what it wrote is there, its close fails with ENOSPC."""

    def __init__(self, writer) -> None:
        self.writer = writer

    def write_metadata(self, *args) -> None:
        self.writer.write_metadata(*args)

    def close(self) -> None:
        self.writer.close()
        raise OSError(errno.ENOSPC, FULL)


def test_an_mcap_recording_cut_short_fails_the_replay(flight_dir, tmp_path, capsys, monkeypatch):
    pytest.importorskip("foxglove")
    from vtolpose.service.outputs import mcap

    real_open = mcap.foxglove.open_mcap
    monkeypatch.setattr(mcap.foxglove, "open_mcap", lambda *a, **kw: FullDiskWriter(real_open(*a, **kw)))
    path = tmp_path / "flight.mcap"
    for command in (["replay", str(flight_dir), "--no-progress", "--sensors", "imu,gps"],
                    ["run", "--replay", str(flight_dir), "--sensors", "imu,gps"]):
        path.unlink(missing_ok=True)
        assert main([*command, "--speed", "0", "--mcap", str(path)]) == 1
        assert capsys.readouterr().out.splitlines()[-1] == f"the mcap output {path} is incomplete: {FULL}"


def test_a_flight_recording_cut_short_fails_the_live_run(flight_dir, tmp_path, capsys, monkeypatch):
    emulators = pytest.importorskip("vtolpose.drivers.emulators")
    from vtolpose.service.outputs import recorder

    class FullDisk:
        """A file that takes 20 kB, then fails like a full disk."""

        room = [20_000]

        def __init__(self, path, mode, **kwargs) -> None:
            self._file = open(path, mode, **kwargs)

        def write(self, data):
            size = len(data.encode() if isinstance(data, str) else data)
            if size > self.room[0]:
                raise OSError(errno.ENOSPC, FULL, str(self._file.name))
            self.room[0] -= size
            return self._file.write(data)

        def __getattr__(self, name):
            return getattr(self._file, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self._file.close()

    class FullDiskRecorder(recorder.FlightRecorder):
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs, opener=FullDisk)

    monkeypatch.setattr(recorder, "FlightRecorder", FullDiskRecorder)
    rec = tmp_path / "rec"
    with emulators.Imu400Emulator.from_dataset(flight_dir) as imu, emulators.NmeaEmulator.from_dataset(flight_dir) as gps:
        config = tmp_path / "vehicle.yaml"
        config.write_text(f"sensors:\n  imu: {{port: {imu.port}}}\n  gps: {{type: nmea, port: {gps.port}}}\n"
                          f"  camera: {{type: none}}\nrun:\n  calibration_file: {flight_dir / 'dataset.yaml'}\n")
        code = main(["run", "--config", str(config), "--duration", "3", "--record", str(rec)])
    out = capsys.readouterr().out
    assert code == 1 and "stopped by duration" in out
    last = out.splitlines()[-1]
    assert last.startswith(f"the flight recording {rec} is incomplete: stopped:") and FULL in last
