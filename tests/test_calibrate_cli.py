"""``vtolpose calibrate imu`` end to end, the blocks' schema check, and the optional matplotlib."""

from __future__ import annotations

import builtins

import numpy as np
import pytest

from vtolpose.config import ConfigError, load_config
from vtolpose.drivers.files.dataset import DatasetWriter
from vtolpose.drivers.simulator import ImuErrorModel, SimulationOptions
from vtolpose.service.calibration import output as calibration_output
from vtolpose.service.calibration.plots import PlotUnavailable, plot_allan
from vtolpose.service.cli import main

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def book(simulated_flight, flight_folder):
    """A 20 s book flight whose gyro has a turn-on bias, and its folder."""
    options = SimulationOptions(imu=ImuErrorModel(gyro_turn_on_bias_std=0.01))
    return simulated_flight("book", 20.0, 5, options), flight_folder("book", 20.0, 5, options)


def test_imu_block_loads_as_config_and_the_figure_is_drawn(book, tmp_path, capsys) -> None:
    flight, root = book
    out = tmp_path / "imu.yaml"
    assert main(["calibrate", "imu", str(root), "--min-static", "5", "--out", str(out)]) == 0
    cfg = load_config(out)
    true_bias = flight.truth.bias_g[: 800].mean(axis=0)  # truth at 100 Hz over the 8 s of rest
    np.testing.assert_allclose(cfg["calibration.imu.gyro_bias"], true_bias, atol=0.1 * np.linalg.norm(true_bias))
    assert cfg["estimator.imu.noise.gyro_noise_density"] == pytest.approx(3e-4, rel=0.2)
    assert cfg["estimator.imu.noise.gyro_random_walk"] is None  # 8 s of rest cannot show it
    assert cfg["calibration.imu.gyro_random_walk"] is None
    assert out.with_suffix(".png").read_bytes().startswith(PNG_MAGIC)
    printed = capsys.readouterr().out
    assert "static stretch: 1.0-9.0 s" in printed and "record an hour or more of rest" in printed


def test_imu_without_rest_writes_nothing(book, tmp_path, capsys) -> None:
    flight, _ = book
    moving = flight.imu.t_ns > flight.imu.t_ns[0] + int(11e9)
    writer = DatasetWriter(tmp_path / "moving")
    writer.write_calibration(flight.calibration, "moving", "the book flight after its rest")
    writer.write_imu(type(flight.imu)(flight.imu.t_ns[moving], flight.imu.gyro[moving], flight.imu.accel[moving]))
    out = tmp_path / "imu.yaml"
    assert main(["calibrate", "imu", str(tmp_path / "moving"), "--out", str(out)]) == 1
    assert "Record the vehicle standing still" in capsys.readouterr().err
    assert not out.exists() and not out.with_suffix(".png").exists()


def test_a_block_the_schema_refuses_is_never_written() -> None:
    with pytest.raises(ConfigError, match=r"calibration\.imu\.gravity"):
        calibration_output.config_block({"calibration": {"imu": {"gravity": -1.0}}}, ["bad"])


def test_missing_matplotlib_says_how_to_get_it(book, monkeypatch, tmp_path, capsys) -> None:
    real_import = builtins.__import__

    def no_matplotlib(name, *args, **kwargs):
        if name.startswith("matplotlib"):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_matplotlib)
    with pytest.raises(PlotUnavailable, match=r"pip install matplotlib \(from a checkout: pip install -e '\.\[plot\]'\), or pass --no-plot"):
        plot_allan(tmp_path / "a.png", None)
    _, root = book
    out = tmp_path / "imu.yaml"
    assert main(["calibrate", "imu", str(root), "--min-static", "5", "--out", str(out)]) == 1
    assert "--no-plot" in capsys.readouterr().err and not out.exists()
    assert main(["calibrate", "imu", str(root), "--min-static", "5", "--out", str(out), "--no-plot"]) == 0
