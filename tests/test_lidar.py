"""The simulated LIDAR and its dataset stream: scanner figures, per-return times, ray casting, files."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.files.lidar import LIDAR_CSV, LIDAR_SENSOR, read_lidar_spec
from vtolpose.drivers.simulator import LandfillScenario, simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.drivers.simulator.lidar import (
    SCENARIO_LIDARS,
    SURVEY_SCANNER,
    URG_04LX,
    GroundMarch,
    cast_rays,
    lidar_with,
    simulate_lidar,
)
from vtolpose.estimator.mapping.geometry import place_returns
from vtolpose.service.cli import main

NOISELESS = dict(range_sigma_m=0.0, range_sigma_fraction=0.0, range_resolution_m=0.0)


@pytest.fixture(scope="module")
def landfill():
    return simulate_flight("landfill", 40.0, 3)


@pytest.fixture(scope="module")
def returns(landfill):
    return simulate_lidar(landfill)


@pytest.fixture(scope="module")
def exact(landfill):
    return simulate_lidar(landfill, lidar_with(SURVEY_SCANNER, **NOISELESS))


def test_scanner_figures():
    assert URG_04LX.beams == 683 and URG_04LX.step_deg == pytest.approx(0.3515625)
    assert URG_04LX.sweep_s == pytest.approx(682 / 1024 * 0.1)  # 66.6 ms of the 100 ms turn
    assert SURVEY_SCANNER.beams == 361 and SURVEY_SCANNER.sweep_s == pytest.approx(0.025)
    angles = SURVEY_SCANNER.angles()
    assert angles[0] == pytest.approx(-np.pi / 4) and angles[-1] == pytest.approx(np.pi / 4)
    with pytest.raises(ValueError, match="field of view"):
        lidar_with(SURVEY_SCANNER, fov_deg=400.0)
    with pytest.raises(ValueError, match="min < max"):
        lidar_with(SURVEY_SCANNER, max_range_m=0.5)


def test_every_return_has_its_own_time_within_the_sweep(landfill, returns):
    spec = returns.spec
    assert len(returns) > 50_000 and np.all(np.diff(returns.t_ns) > 0)
    for a, b in returns.scan_bounds()[100:110].tolist():
        t, scan = returns.t_ns[a:b], returns.scan[a]
        start = int(landfill.truth.t_ns[0]) + round(scan * 1e9 / spec.scan_rate_hz)
        beam = np.round((returns.angle[a:b] - spec.angles()[0]) / np.radians(spec.step_deg)).astype(int)
        assert np.array_equal(t, start + np.round(beam * spec.beam_interval_s * 1e9).astype(np.int64))
        assert t[-1] - t[0] > 0.9 * spec.sweep_s * 1e9  # one scan spans its whole 25 ms sweep


def test_noise_free_returns_lie_on_the_ground(landfill, exact):
    k = landfill.trajectory.kinematics((exact.t_ns - landfill.truth.t_ns[0]) * 1e-9)
    points = place_returns(k.p, k.q(), exact.spec.mount, exact.angle, exact.range_m)
    ground = landfill.scenario.ground_height(points[:, 0], points[:, 1])
    assert np.max(np.abs(points[:, 2] - ground)) < 1e-6


def test_range_noise_is_the_scanner_s_and_seeded(landfill, exact, returns):
    noisy = returns
    again = simulate_lidar(landfill, scans_per_chunk=7)  # the same draws however the work is cut
    assert np.array_equal(noisy.range_m, again.range_m) and np.array_equal(noisy.t_ns, again.t_ns)
    common, i, j = np.intersect1d(exact.t_ns, noisy.t_ns, return_indices=True)
    err = noisy.range_m[j] - exact.range_m[i]
    assert len(common) > 0.99 * len(exact)
    assert np.std(err) == pytest.approx(0.02, rel=0.05) and abs(np.mean(err)) < 0.001
    other = simulate_lidar(dataclasses.replace(landfill, seed=4))
    assert not np.array_equal(other.range_m[:1000], noisy.range_m[:1000])


def test_the_landfill_is_no_steeper_than_its_march_assumes():
    ground = LandfillScenario().ground_height
    n, e = np.meshgrid(np.arange(-100.0, 500.0, 0.5), np.arange(-150.0, 450.0, 0.5), indexing="ij")
    d = ground(n, e)
    slope = np.hypot(np.diff(d, axis=0)[:, :-1], np.diff(d, axis=1)[:-1, :]) / 0.5
    assert slope.max() < 0.5 * SCENARIO_LIDARS["landfill"][1].max_slope


def test_cast_finds_the_first_hit_of_a_step_and_misses_beyond_range():
    def table(n, e):  # a 3.5 cm step (a book) on a table top at 0, the floor 0.75 m below beyond |n| > 1
        n = np.asarray(n, dtype=float)
        return np.where(np.abs(n) <= 0.1, -0.035, np.where(np.abs(n) <= 1.0, 0.0, 0.75))

    march = GroundMarch(max_slope=1.0, max_step_m=0.02, min_step_m=0.001)
    down = np.array([0.0, 0.0, 1.0])
    grazing = np.array([np.cos(0.05), 0.0, np.sin(0.05)])  # 3 cm over the table, towards the book's side 0.2 m away
    origin = np.array([[0.0, 0.0, -0.5], [-0.3, 0.0, -0.03], [0.0, 0.0, -0.5], [2.0, 0.0, -0.5]])
    direction = np.array([down, grazing, -down, down])
    t = cast_rays(origin, direction, table, 4.0, march)
    assert t[0] == pytest.approx(0.465, abs=1e-6)  # onto the book's cover
    hit = origin[1] + t[1] * grazing  # the side of the book, not the table behind it
    assert hit[0] == pytest.approx(-0.1, abs=1e-6) and -0.035 <= hit[2] <= -0.015
    assert np.isinf(t[2])  # straight up: nothing
    assert t[3] == pytest.approx(1.25, abs=1e-6)  # the floor


def test_dataset_round_trip_and_replay_passes_it_through(landfill, returns, tmp_path):
    root = write_flight(landfill, tmp_path / "lf", lidar=returns)
    back = Dataset.open(root).lidar()
    assert back.spec == returns.spec and back.ground_scenario == "landfill"
    assert np.array_equal(back.t_ns, returns.t_ns) and np.array_equal(back.scan, returns.scan)
    assert np.max(np.abs(back.range_m - returns.range_m)) < 1e-9  # ranges are on the 1 mm grid already
    assert np.max(np.abs(back.angle - returns.angle)) <= 5e-8
    # A corrupt line is counted and skipped by the tolerant reader, the rest read alike.
    lines = (root / LIDAR_CSV).read_text().splitlines()
    lines[5000] = "garbage,1,2"
    lines[6000] = lines[6000].rsplit(",", 1)[0] + ",-1.0"
    (root / LIDAR_CSV).write_text("\n".join(lines) + "\n")
    dataset = Dataset.open(root)
    damaged = dataset.lidar()
    assert len(damaged) == len(returns) - 2 and dataset.skipped[LIDAR_CSV] == 2
    report = tmp_path / "r.json"
    assert main(["-q", "replay", str(root), "--sensors", "imu,gps", "--report", str(report), "--no-progress"]) == 0
    notes = json.loads(report.read_text())["notes"]
    assert any("lidar0" in n and "passed through, not fused" in n and str(len(returns)) in n for n in notes)


def test_sensor_yaml_errors_name_the_key(landfill, returns, tmp_path):
    root = write_flight(landfill, tmp_path / "lf", lidar=returns)
    path = root / LIDAR_SENSOR
    path.write_text(path.read_text().replace("step_deg: 0.25", "step_deg: fast"))
    with pytest.raises(ValueError, match="sensor.yaml: step_deg: expected a finite number"):
        read_lidar_spec(root)
    path.unlink()
    with pytest.raises(FileNotFoundError, match="R_BL and t_BL"):
        Dataset.open(root).lidar()


def test_simulate_command_takes_the_scanner_s_figures(tmp_path, capsys):
    out = tmp_path / "book"
    args = ["simulate", "--scenario", "book", "--duration", "3", "--no-camera", "--out", str(out), "--lidar",
            "--lidar-fov", "120", "--lidar-step", "1", "--lidar-rate", "20", "--lidar-range-sigma", "0.005",
            "--lidar-max-range", "3"]
    assert main(args) == 0
    assert "lidar" in capsys.readouterr().out
    spec, scenario = read_lidar_spec(out)
    assert (spec.model, spec.fov_deg, spec.step_deg, spec.scan_rate_hz, spec.range_sigma_m, spec.max_range_m) == (
        "Hokuyo URG-04LX", 120.0, 1.0, 20.0, 0.005, 3.0)
    returns = Dataset.open(out).lidar()
    assert scenario == "book" and returns.scan.max() == 59 and np.all(np.abs(returns.angle) <= np.radians(60.0) + 1e-7)
    assert main(["-q", "simulate", "--scenario", "book", "--duration", "3", "--no-camera", "--out", str(out),
                 "--force", "--lidar", "--lidar-step", "0"]) == 1
    assert "angular step" in capsys.readouterr().err
