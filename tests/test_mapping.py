"""The reference mapper: the height grid, known volumes, per-return poses, scores, the map command."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
from dataclasses import dataclass

import numpy as np
import pytest

from vtolpose.drivers.files.tum import write_tum
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.drivers.simulator.lidar import SURVEY_SCANNER, GroundMarch, lidar_with, simulate_lidar
from vtolpose.drivers.simulator.trajectory import EulerTrajectory, SineMotion
from vtolpose.estimator.mapping.geometry import place_returns
from vtolpose.estimator.mapping.height_grid import HeightGrid
from vtolpose.estimator.mapping.survey import coverage_fraction, score_map
from vtolpose.service.cli import main
from vtolpose.service.mapping.mapper import map_returns
from vtolpose.service.mapping.poses import one_pose_per_scan, trajectory_window, window_poses

NOISELESS = lidar_with(SURVEY_SCANNER, range_sigma_m=0.0, range_sigma_fraction=0.0, range_resolution_m=0.0)
MARCH = GroundMarch(max_slope=1.0, max_step_m=0.5, min_step_m=0.002)


@dataclass(frozen=True)
class World:
    """A test ground: flat at ``up`` metres above the origin, an optional block on it, an optional slope."""

    up: float = 0.0
    block: tuple[float, float, float, float, float] | None = None  # n0, n1, e0, e1, height
    slope_e: float = 0.0

    def ground_height(self, n, e):
        n, e = np.broadcast_arrays(np.asarray(n, dtype=float), np.asarray(e, dtype=float))
        up = self.up + self.slope_e * e
        if self.block is not None:
            n0, n1, e0, e1, h = self.block
            up = up + np.where((n >= n0) & (n < n1) & (e >= e0) & (e < e1), h, 0.0)
        return -up


def sines(rows):
    table = np.array(rows, dtype=float)
    return table[..., 0], table[..., 1], table[..., 2]


def flight_over(world: World, position, attitude, duration_s: float = 30.0):
    """A flight of ``duration_s`` with the given sine motions over ``world`` (IMU and GPS are not used)."""
    base = simulate_flight("landfill", duration_s, 1)
    trajectory = EulerTrajectory(SineMotion(*position, 0.0, 1.0), SineMotion(*attitude, 0.0, 1.0))
    return dataclasses.replace(base, scenario=world, trajectory=trajectory)


def true_window(flight, rate_hz: float = 1000.0):
    t = np.arange(int(flight.duration_s * rate_hz) + 1) / rate_hz
    k = flight.trajectory.kinematics(t)
    return trajectory_window(flight.truth.t_ns[0] + np.round(t * 1e9).astype(np.int64), k.p, k.q())


# A slow sweep back and forth at 30 m over a 60 x 60 m area, level, heading north.
SWEEP = (np.array([30.0, 25.0, -30.0]), *sines([[(18.0, 0.4, 0.0)], [(22.0, 0.13, 0.0)], [(0.0, 1.0, 0.0)]]))
LEVEL = (np.zeros(3), *sines([[(0.0, 1.0, 0.0)]] * 3))


def test_grid_cells_means_and_tiles_across_the_origin():
    grid = HeightGrid(0.5)
    points = np.array([[0.1, 0.1, -1.0], [0.4, 0.2, -3.0], [-0.1, 0.1, -2.0], [-40.2, 70.3, 5.0], [np.nan, 0, 0]])
    assert grid.add(points) == 4
    hmap = grid.snapshot()
    n, e = hmap.centres()
    cell = (n == 0.25) & (e == 0.25)
    assert hmap.height[cell] == [2.0] and hmap.count[cell] == [2]  # mean of the two, up positive
    assert hmap.height[(n == -0.25) & (e == 0.25)] == [2.0]
    assert hmap.height[(n == -40.25) & (e == 70.25)] == [-5.0]  # another tile, south-east
    assert hmap.covered.sum() == 3 and hmap.extent() == (0.0, 70.5, -40.5, 0.5)
    with pytest.raises(ValueError, match="cell size"):
        HeightGrid(0.0)


def test_coverage_counts_holes_not_the_outline():
    covered = np.zeros((10, 10), dtype=bool)
    covered[2:8, 2:8] = True
    assert coverage_fraction(covered) == 1.0
    covered[4, 4] = False
    assert coverage_fraction(covered) == pytest.approx(35 / 36)


def test_flat_ground_volume_is_known_exactly():
    world = World(up=2.0)
    flight = flight_over(world, SWEEP, LEVEL)
    returns = simulate_lidar(flight, NOISELESS, MARCH)
    run = map_returns(returns, window_poses(true_window(flight)), 1.0)
    score = score_map(run.grid.snapshot(), base_up_m=0.0, ground_down=world.ground_height)
    assert run.scans_placed == run.scans and score.cells > 2000
    assert score.volume_m3 == pytest.approx(2.0 * score.area_m2, rel=1e-7)
    assert score.true_volume_m3 == pytest.approx(2.0 * score.area_m2, rel=1e-12)
    assert abs(score.volume_error_m3) < 1e-6 * score.volume_m3 and score.height_rmse_m < 1e-6
    # Below the base, nothing is counted; half-way up, half the volume.
    assert score_map(run.grid.snapshot(), base_up_m=3.0).volume_m3 == 0.0
    assert score_map(run.grid.snapshot(), base_up_m=1.0).volume_m3 == pytest.approx(score.area_m2, rel=1e-7)
    # With the scanner's 2 cm range noise the volume is off only by the noise averaged over the returns.
    noisy = map_returns(simulate_lidar(flight, SURVEY_SCANNER, MARCH), window_poses(true_window(flight)), 1.0)
    s = score_map(noisy.grid.snapshot(), 0.0, world.ground_height)
    # Per cell the noise is averaged over its returns (38 here): 2 cm / sqrt(38) = 3 mm.
    assert abs(s.height_bias_m) < 4 * 0.02 / np.sqrt(s.returns) and 0.002 < s.height_rmse_m < 0.02 / np.sqrt(20)


def test_a_block_of_known_volume_is_measured_within_its_edge_cells():
    world = World(block=(20.0, 40.0, 15.0, 30.0, 3.0))  # 20 x 15 x 3 m = 900 m3 on flat ground at the base
    flight = flight_over(world, SWEEP, LEVEL)
    run = map_returns(simulate_lidar(flight, NOISELESS, MARCH), window_poses(true_window(flight)), 1.0)
    score = score_map(run.grid.snapshot(), 0.0, world.ground_height)
    assert score.true_volume_m3 == pytest.approx(900.0)
    # Only the 70 cells along the block's edges can hold returns off its walls (at most 3 m x 1 m2 each).
    assert abs(score.volume_error_m3) < 0.03 * 900.0  # measured: -12 m3 (-1.4 %)


def test_a_fast_yaw_during_a_scan_needs_each_return_s_own_pose():
    world = World(slope_e=0.3)
    yaw = (np.zeros(3), *sines([[(0.0, 1.0, 0.0)], [(0.0, 1.0, 0.0)], [(1.0, 6.0, 0.0)]]))  # up to 6 rad/s of yaw
    hover = (np.array([0.0, 0.0, -20.0]), *sines([[(0.0, 1.0, 0.0)]] * 3))
    flight = flight_over(world, hover, yaw, duration_s=6.0)
    returns = simulate_lidar(flight, NOISELESS, MARCH)
    window = true_window(flight)
    k = flight.trajectory.kinematics((returns.t_ns - flight.truth.t_ns[0]) * 1e-9)
    truth = place_returns(k.p, k.q(), returns.spec.mount, returns.angle, returns.range_m)  # where each beam hit

    def placed(source):
        out = [place_returns(*source(returns.t_ns[s]), returns.spec.mount, returns.angle[s], returns.range_m[s])
               for s in returns.scans()]
        return np.concatenate(out)

    per_return = np.linalg.norm(placed(window_poses(window)) - truth, axis=1)
    per_scan = np.linalg.norm(placed(one_pose_per_scan(window)) - truth, axis=1)
    assert per_return.max() < 1e-3
    assert per_scan.max() > 2.0 and np.sqrt(np.mean(per_scan**2)) > 0.5  # a 25 ms sweep turns up to 8.6 degrees
    on_slope = [score_map(map_returns(returns, source, 0.5).grid.snapshot(), 0.0, world.ground_height).height_rmse_m
                for source in (window_poses(window), one_pose_per_scan(window))]
    # Per return, only the grid's own cost is left (the slope within a 0.5 m cell): 2.6 cm against 7.9 cm.
    assert on_slope[0] < 0.04 and on_slope[1] > 2.5 * on_slope[0]


@pytest.fixture(scope="module")
def mapped_dataset(tmp_path_factory):
    """A 45 s landfill flight with its LIDAR, and its truth resampled into a TUM file with an error added."""
    root = tmp_path_factory.mktemp("map") / "landfill"
    flight = simulate_flight("landfill", 45.0, 2)
    write_flight(flight, root, lidar=simulate_lidar(flight))
    truth = flight.truth
    p = truth.p + np.array([0.0, 0.0, -0.5])  # 0.5 m too high: every height +0.5 m
    write_tum(root.parent / "high.txt", truth.t_ns, p, truth.q)
    return root


def test_map_command_scores_truth_and_an_offset_trajectory(mapped_dataset, tmp_path, capsys):
    report = tmp_path / "m.json"
    assert main(["map", str(mapped_dataset), "--true-poses", "--report", str(report)]) == 0
    truth = json.loads(report.read_text())["map"]
    assert truth["height_rmse_m"] < 0.05 and abs(truth["volume_error_percent"]) < 0.5 and truth["coverage"] > 0.95
    assert main(["map", str(mapped_dataset), "--trajectory", str(mapped_dataset.parent / "high.txt"), "--explain",
                 "--report", str(report), "--png", str(tmp_path / "fig")]) == 0
    doc = json.loads(report.read_text())
    high = doc["map"]
    assert high["height_bias_m"] == pytest.approx(0.5, abs=0.01)
    assert high["volume_error_m3"] == pytest.approx(0.5 * high["area_m2"], rel=0.02)  # the base is below almost all
    explained = {m["label"]: m for m in doc["explain"]["maps"]}
    assert explained["trajectory: position only (true attitude)"]["height_bias_m"] == pytest.approx(0.5, abs=0.01)
    assert abs(explained["trajectory: attitude only (true position)"]["height_bias_m"]) < 0.01
    assert doc["explain"]["pose_errors"]["height_error_mean_m"] == pytest.approx(0.5, abs=1e-6)
    assert (tmp_path / "fig-height.png").stat().st_size > 10_000 and (tmp_path / "fig-error.png").is_file()
    out = capsys.readouterr().out
    assert "what the map's error comes from" in out and "volume above 0 m" in out
    # A mapper's own calibration: a LIDAR clock offset and a boresight error each cost the true-pose map.
    for option in (["--time-offset", "0.2"], ["--boresight", "1,0,0"]):
        assert main(["-q", "map", str(mapped_dataset), "--true-poses", "--report", str(report), *option]) == 0
        assert json.loads(report.read_text())["map"]["height_rmse_m"] > 3 * truth["height_rmse_m"], option


def test_map_command_errors_say_what_is_missing(mapped_dataset, tmp_path, capsys):
    assert main(["map", str(mapped_dataset), "--true-poses", "--cell", "-1"]) == 1
    assert "--cell" in capsys.readouterr().err
    assert main(["map", "--true-poses"]) == 1
    assert "which returns to map" in capsys.readouterr().err
    assert main(["map", str(mapped_dataset), "--true-poses", "--explain"]) == 1
    assert "--explain" in capsys.readouterr().err
    assert main(["map", str(mapped_dataset), "--true-poses", "--boresight", "1,0"]) == 1
    assert "ROLL,PITCH,YAW" in capsys.readouterr().err
    assert main(["map", str(mapped_dataset), "--true-poses", "--kind", "smoothed"]) == 1
    assert "--kind" in capsys.readouterr().err
    bare = tmp_path / "bare"
    write_flight(simulate_flight("landfill", 5.0, 1), bare)
    assert main(["map", str(bare), "--true-poses"]) == 1
    assert "no LIDAR returns" in capsys.readouterr().err


def test_demo_maps_the_flight_with_true_poses_and_each_kind_of_pose(tmp_path, capsys):
    """True poses, then per sensor set the filter, the fixed lag and the smoothed trajectory, each its own map."""
    out_dir = tmp_path / "d"
    assert main(["-q", "demo", "--scenario", "landfill", "--duration", "30", "--lidar", "--out", str(out_dir)]) == 0
    out = capsys.readouterr().out
    sets = ["IMU+GPS", "IMU+camera+GPS"] if importlib.util.find_spec("skimage") else ["IMU+GPS"]
    kinds = ["filter", "fixed lag 2 s", "smoothed"]
    labels = ["true poses"] + [f"{name} {kind}" for name in sets for kind in kinds]
    table = out[out.index("LIDAR map"):].splitlines()
    rows = {line.split("  ")[1].strip(): line.split() for line in table[2:2 + len(labels)]}
    assert list(rows) == labels
    rmse = {label: float(cells[-5]) for label, cells in rows.items()}  # columns: cells RMSE bias volume error error%
    volume = {label: float(cells[-3]) for label, cells in rows.items()}
    assert rmse["true poses"] < 0.05
    assert min(rmse[label] for label in labels[1:]) > 2 * rmse["true poses"]  # the poses cost more than the grid
    for name in sets:  # three different trajectories, three different maps
        assert len({volume[f"{name} {kind}"] for kind in kinds}) == 3, name
    # IMU + GPS on this flight: the later fixes pull the smoothed heights in, the map follows.
    assert rmse["IMU+GPS smoothed"] < rmse["IMU+GPS filter"]
    errors = out[out.index("the poses at the returns' times"):].splitlines()
    assert [line.split("  ")[1].strip() for line in errors[3:3 + len(labels) - 1]] == labels[1:]
    for stem in ["imu-gps"] + (["imu-camera-gps"] if len(sets) == 2 else []):
        for kind in ("filtered", "fixed-lag", "smoothed"):
            assert (out_dir / f"trajectory-{stem}-{kind}.txt").stat().st_size > 10_000, (stem, kind)


def test_the_volume_follows_the_height_error_over_the_cells_not_over_the_returns(mapped_dataset):
    """0.5 m too high only during the climb (its returns packed into a few cells, low over the pad):
    the mean over the returns weighs those cells by their many returns; the volume does not."""
    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.service.mapping.mapper import pose_errors
    from vtolpose.service.mapping.poses import truth_window

    dataset = Dataset.open(mapped_dataset)
    returns, truth = dataset.lidar(), truth_window(dataset)
    p = truth.p.copy()
    early = truth.t_ns < truth.t_ns[0] + 20_000_000_000  # the climb: returns from 13 s, 45 m up by 27 s
    p[early, 2] -= 0.5
    estimate = trajectory_window(truth.t_ns, p, truth.q)
    maps = [map_returns(returns, window_poses(w), 1.0).grid.snapshot() for w in (truth, estimate)]
    assert np.array_equal(maps[0].count, maps[1].count)  # a height error moves no return to another cell
    covered = maps[0].covered
    volume_change_m3 = float(np.sum(maps[1].height[covered] - maps[0].height[covered]))  # 1 m² cells, base below all
    errors = pose_errors(estimate, truth, returns, 1.0)
    assert errors["cells"] == int(covered.sum())
    assert errors["height_error_mean_m"] * errors["cells"] == pytest.approx(volume_change_m3, rel=1e-6)
    assert errors["height_error_mean_returns_m"] > 2 * errors["height_error_mean_m"] > 0
