"""Configuration: defaults and schema agree; bad keys and types are refused with the key named."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from vtolpose import config
from vtolpose.config import ConfigError, load_config
from vtolpose.config.schema import SCHEMA


def test_every_default_has_a_schema_entry_and_back():
    flat = config._flatten(config.default_config())
    assert set(flat) == set(SCHEMA)


def test_defaults_load_and_are_typed():
    cfg = load_config()
    assert cfg["estimator.variant"] == "biases"
    assert isinstance(cfg["estimator.gps.gate_chi2"], float)
    assert config.get(cfg, "estimator.init")["static_window_s"] == 2.0


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "cfg.yaml"
    path.write_text(text)
    return path


def test_user_file_overrides_only_its_keys(tmp_path):
    cfg = load_config(write(tmp_path, "estimator:\n  variant: thesis\n"))
    assert cfg["estimator.variant"] == "thesis"
    assert cfg["estimator.gps.gate_chi2"] == pytest.approx(16.27)


@pytest.mark.parametrize(
    "text, message",
    [
        ("estimator:\n  varient: thesis\n", r"unknown key 'estimator\.varient' \(did you mean 'estimator\.variant'\?\)"),
        ("estimator:\n  variant: kalman\n", r"key 'estimator\.variant': must be one of thesis, biases"),
        ("estimator:\n  gps:\n    gate_chi2: lots\n", r"key 'estimator\.gps\.gate_chi2': expected a finite number"),
        ("estimator:\n  gps:\n    sigma_floor_m: -1\n", r"sigma_floor_m': must be greater than 0"),
        ("vehicle:\n  system_id: 300\n", r"system_id': must be at most 255"),
        ("vehicle:\n  system_id: true\n", r"system_id': expected an integer"),
        ("estimator: 5\n", r"key 'estimator': expected a section"),
        ("estimator: [\n", r"not valid YAML \(line"),
        ("replay:\n  sensors: [imu, lidar]\n", r"unknown item\(s\) \['lidar'\]"),
    ],
)
def test_bad_files_are_refused_with_the_key_named(tmp_path, text, message):
    with pytest.raises(ConfigError, match=message):
        load_config(write(tmp_path, text))


def test_missing_file_and_cross_checks(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match=r"estimator\.alignment\.hypotheses"):
        load_config(write(tmp_path, "estimator:\n  alignment:\n    hypotheses: 2\n"))


def test_null_only_where_allowed(tmp_path):
    assert load_config(write(tmp_path, "estimator:\n  heading:\n    deg: null\n"))["estimator.heading.deg"] is None
    with pytest.raises(ConfigError, match="must not be null"):
        load_config(write(tmp_path, "estimator:\n  variant: null\n"))


def test_default_yaml_is_commented_and_parseable():
    text = (Path(config.__file__).parent / "default.yaml").read_text()
    assert yaml.safe_load(text)
    assert text.count("#") > 40  # every section says what it is for


def test_calibration_section_overrides_the_dataset_calibration():
    from vtolpose.drivers.simulator import simulate_flight
    from vtolpose.drivers.simulator.render import default_camera
    from vtolpose.service.runtime.wiring import calibration_with_overrides

    cal = simulate_flight("book", 2.0, 0).calibration
    cfg = load_config(None, {"calibration": {"gps": {"time_offset_s": -0.12, "lever_arm_b": [0.1, 0.0, -0.2]},
                                             "imu": {"gravity": 9.81, "gyro_noise_density": [1e-3, 2e-3, 3e-3]}}})
    out = calibration_with_overrides(cfg, cal)
    assert out.gps.time_offset_s == -0.12 and out.imu.gravity == 9.81
    assert list(out.imu.noise.gyro_noise_density) == [1e-3, 2e-3, 3e-3]  # the Allan figure is the noise model
    assert np.array_equal(out.imu.noise.accel_noise_density, cal.imu.noise.accel_noise_density)  # null: kept
    assert list(out.gps.lever_arm_b) == [0.1, 0.0, -0.2]
    assert cal.gps.time_offset_s == 0.0  # the original is untouched
    cam_cfg = load_config(None, {"calibration": {"camera": {"fx": 600.0, "k1": -0.1, "time_offset_s": 0.037}}})
    with pytest.raises(ConfigError, match="calibration.camera.fx.*no camera block"):
        calibration_with_overrides(cam_cfg, cal)
    from dataclasses import replace

    with_cam = calibration_with_overrides(cam_cfg, replace(cal, camera=default_camera()))
    assert with_cam.camera.fx == 600.0 and with_cam.camera.distortion[0] == -0.1 and with_cam.camera.time_offset_s == 0.037
