"""The visual-inertial start: tracks, the window solver and the start it hands to the filter.

Frames here are synthetic (ground points of the simulated scene projected through the camera
model with pixel noise, each point with its own binary descriptor), so these tests need no
rendering; the rendered flights are in tests/test_start_in_flight.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from vtolpose.drivers.simulator import SimulationOptions, simulate_flight
from vtolpose.drivers.simulator.floor import FloorScenario, start_options
from vtolpose.drivers.simulator.motion_profiles import PROFILES
from vtolpose.drivers.simulator.render import default_camera
from vtolpose.estimator.core.rotation import euler_from_quat, quat_to_rot
from vtolpose.estimator.inertial.imu_delta import ImuDownsampler
from vtolpose.estimator.init.tracks import FeatureTracker
from vtolpose.estimator.init.visual_inertial import (Gauge, VisualInertialInitializer, VisualInertialOptions,
                                                      velocity_sigma_limit)
from vtolpose.estimator.init.window_solver import WindowFailure, acceleration_spread, scale_sigma, solve_window
from vtolpose.estimator.vision.camera_model import CameraModel
from vtolpose.estimator.vision.features import FrameFeatures

CAMERA = default_camera()


class SyntheticCamera:
    """Frames of a simulated flight: random ground points seen from the true pose, ``noise_px`` on each pixel."""

    def __init__(self, flight, noise_px: float = 0.5, span_m: float = 2.0, seed: int = 0, per_frame: int = 200) -> None:
        self.flight, self.noise, self.per_frame = flight, noise_px, per_frame
        self.model = CameraModel(CAMERA)
        self.rng = np.random.default_rng(seed)
        c0 = flight.trajectory.kinematics(np.zeros(1)).p[0]
        n = 5000
        pts = np.column_stack([c0[0] + self.rng.uniform(-span_m, span_m, n), c0[1] + self.rng.uniform(-span_m, span_m, n), np.zeros(n)])
        pts[:, 2] = flight.scenario.ground_height(pts[:, 0], pts[:, 1])
        self.points = pts
        self.descriptors = self.rng.integers(0, 256, (n, 32), dtype=np.uint8)

    def frame(self, t_ns: int) -> FrameFeatures:
        k = self.flight.trajectory.kinematics(np.array([(t_ns - int(self.flight.imu.t_ns[0])) * 1e-9]))
        R, p = k.rotation()[0], k.p[0]
        in_cam = (self.points - (p + R @ CAMERA.t_BC)) @ (R @ CAMERA.R_BC)
        front = np.flatnonzero(in_cam[:, 2] > 0.1)
        uv, _ = self.model.project(in_cam[front])
        inside = self.model.in_image(uv, 5.0)
        idx, uv = front[inside], uv[inside] + self.rng.normal(0.0, self.noise, (int(inside.sum()), 2))
        pick = self.rng.permutation(len(idx))[: self.per_frame]
        return FrameFeatures(t_ns, uv[pick], self.descriptors[idx[pick]], np.ones(len(pick)), (CAMERA.height, CAMERA.width),
                             binary=True)


def run_start(flight, options: VisualInertialOptions | None = None, seconds: float = 6.0, noise_px: float = 0.5):
    """Feed IMU deltas and frames as the estimator does (the IMU brought to each frame's time); the start, or None."""
    init = VisualInertialInitializer(CAMERA, flight.calibration.imu.noise, flight.calibration.imu.gravity, 1.0, options)
    synthetic = SyntheticCamera(flight, noise_px, span_m=2.0 if flight.scenario_name == "book" else 200.0)
    downsampler = ImuDownsampler(100.0)
    t_first = int(flight.imu.t_ns[0])
    frames = t_first + np.round(np.arange(0.0, seconds, 1.0 / CAMERA.rate_hz) * 1e9).astype(np.int64)
    f = 0
    for i, t in enumerate(flight.imu.t_ns.tolist()):
        while f < len(frames) and frames[f] <= t:
            for delta in (downsampler.flush(), downsampler.hold(int(frames[f]))):
                if delta is not None:
                    init.add_delta(delta)
            start = init.add_frame(synthetic.frame(int(frames[f])), Gauge(np.zeros(3), 0.0))
            if start is not None:
                return init, start
            f += 1
        if f >= len(frames):
            break
        delta = downsampler.add(t, flight.imu.gyro[i], flight.imu.accel[i])
        if delta is not None:
            init.add_delta(delta)
    return init, None


def test_tracks_follow_points_across_frames_and_say_when_the_scene_moves():
    flight = simulate_flight("book", 2.0, 3, SimulationOptions(start_s=20.0))
    synthetic = SyntheticCamera(flight, noise_px=0.3)
    tracker = FeatureTracker(CameraModel(CAMERA))
    t0 = int(flight.imu.t_ns[0])
    for k in range(6):
        tracker.add(synthetic.frame(t0 + k * 133_333_333))
    last = tracker.frames[-1]
    lengths = np.array([sum(int(t) in set(f.track_ids.tolist()) for f in tracker.frames) for t in last.track_ids])
    assert np.mean(lengths >= 3) > 0.5  # most of the last frame's points were seen before
    assert tracker.image_moving(last.t_ns, 1.0, 2.0)  # the arm moves the camera: the scene moves
    still = SyntheticCamera(simulate_flight("book", 2.0, 3), noise_px=0.3)  # on the spot (10 s of rest)
    calm = FeatureTracker(CameraModel(CAMERA))
    for k in range(6):
        calm.add(still.frame(t0 + k * 133_333_333))
    assert not calm.image_moving(calm.frames[-1].t_ns, 1.0, 2.0)


def test_a_hover_moves_the_scene_though_no_frame_does():
    """A hover's wander moves the image about half a pixel a frame, inside the features' noise from one frame to the
    next, but the same way for seconds: over the still window the scene has moved. Taken for a vehicle at rest, the
    hover got a still start, guessed depths and, at the first baseline of its own drift, a scale 2-3 times wrong
    with a covariance of a few per cent (the camera matrix's hover cell, NEES 39)."""
    scenario = FloorScenario(profile=PROFILES["hover"])
    flight = simulate_flight(scenario, 3.0, 1, SimulationOptions(**start_options("motion", scenario)))
    synthetic = SyntheticCamera(flight, noise_px=0.3)
    tracker = FeatureTracker(CameraModel(CAMERA))
    t0 = int(flight.imu.t_ns[0])
    for k in range(30):
        tracker.add(synthetic.frame(t0 + k * 66_666_667))
    flows = np.array([f.flow_px for f in tracker.frames][1:])
    assert np.nanmax(flows) < 2.0  # no frame moved the scene more than the threshold
    assert tracker.image_moving(tracker.frames[-1].t_ns, 2.0, 2.0)


def test_the_epipolar_test_of_a_sample_without_motion_keeps_its_matches():
    """Points that did not move fit no essential matrix: OpenCV 5.1's five-point solver refuses such a
    sample with an error (5.0 returned a matrix that all of them fit). The tracker must keep them all either
    way, as when there are too few to test, not fail the frame."""
    rng = np.random.default_rng(0)
    x0 = rng.uniform(-0.3, 0.3, size=(40, 2))
    tracker = FeatureTracker(CameraModel(CAMERA))
    kept = tracker._epipolar_inliers(x0, x0.copy())
    assert kept.shape == (40,) and kept.dtype == bool and kept.all()


def test_book_in_flight_converges_to_the_truth_within_its_covariance():
    flight = simulate_flight("book", 6.0, 3, SimulationOptions(start_s=20.0))
    init, start = run_start(flight)
    assert start is not None, init.last_failure
    t_s = (start.t_ns - int(flight.imu.t_ns[0])) * 1e-9
    assert t_s < 3.0
    truth = flight.trajectory.kinematics(np.array([t_s]))
    q_true = truth.q()[0]
    sd = np.sqrt(np.diag(start.cov))
    # Roll and pitch are observable (gravity); heading and position are the frame's gauge.
    err_rp = euler_from_quat(start.q)[:2] - euler_from_quat(q_true)[:2]
    assert np.all(np.abs(err_rp) < 3.0 * sd[6:8] + 1e-3)
    # Velocity in the body frame is free of the heading gauge.
    v_err = quat_to_rot(start.q).T @ start.v - quat_to_rot(q_true).T @ truth.v[0]
    assert np.linalg.norm(v_err) < 3.0 * np.linalg.norm(sd[3:6])
    assert np.all(np.abs(start.b_g - flight.truth.bias_g[0]) < 3.0 * sd[9:12] + 1e-4)
    assert start.depth_sigma_rel < 0.1 and len(start.landmarks) >= 10
    assert start.landmarks.shape == (len(start.descriptors), 6) and start.cov.shape == (15 + 6 * len(start.landmarks),) * 2
    # Positive semi-definite (each anchor is the camera centre, as in any new landmark: no own freedom).
    assert np.linalg.eigvalsh(start.cov).min() > -1e-12 * np.abs(start.cov).max()
    assert np.all(np.diagonal(start.cov) > 0.0)
    # The landmarks are where the points are: each anchored at the camera, its ray and depth to the point.
    from vtolpose.estimator.vision.landmarks import landmark_points
    depths = 1.0 / start.landmarks[:, 5]
    assert np.all((depths > 0.3) & (depths < 2.0))  # the table is 0.5–1 m under the rig
    assert np.all(np.isfinite(landmark_points(start.landmarks)))


def test_a_steady_cruise_does_not_start_it_cannot_see_the_scale():
    """Straight and level at 8 m/s: the IMU feels nothing but gravity, so nothing fixes the scale. No fixed
    excitation limit says so: the window's own information leaves the scale's sigma wide (or the alignment
    finds no motion that fits), and the initializer says which, with what it measured."""
    flight = simulate_flight("landfill", 5.0, 3, SimulationOptions(start_s=45.0))
    init, start = run_start(flight, seconds=4.9)
    assert start is None and init.attempts > 0
    checks = [p.check for p in init.history]
    assert set(checks) <= {"window", "motion", "scale"} and "scale" in checks, checks
    scale = next(p for p in init.history if p.check == "scale")
    assert scale.scale_sigma_rel > 0.25 and scale.excitation < 0.05 and scale.gravity_sigma_deg is not None
    assert scale.describe().startswith("initialising: 0.0") and "scale sigma" in scale.describe() and scale.describe().isascii()
    assert init.progress.as_dict()["text"] == init.progress.describe() and init.progress.attempts == init.attempts


def test_the_scale_sigma_comes_from_the_window_and_is_published():
    """A lively window (the book flight in the air) knows its scale to a few percent, and the start says so."""
    flight = simulate_flight("book", 6.0, 3, SimulationOptions(start_s=20.0))
    init, start = run_start(flight)
    assert start is not None, init.last_failure
    assert 0.0 < start.sigma_scale_rel < 0.05 and "scale sigma" in start.describe()
    assert [p.check for p in init.history][-1] == "confirming"  # passed once, started on the next agreeing window
    strict = VisualInertialOptions(max_scale_sigma_rel=0.5 * start.sigma_scale_rel)
    init, start = run_start(flight, strict, seconds=2.5)
    assert start is None and init.progress.check == "scale", init.progress.describe()


def test_a_velocity_known_as_well_as_the_scale_passes_the_velocity_test():
    """The window knows a speed only as well as its scale: wherever the scale test passes (sigma up to
    max_scale_sigma_rel), a velocity with that relative sigma passes too, at any speed (the landfill's
    start in the air: 8 m/s, scale known to 8.6 %, velocity to 0.71 m/s)."""
    options = VisualInertialOptions()
    for speed in (0.0, 0.5, 2.0, 8.0, 20.0):
        for scale_sigma_rel in np.linspace(0.0, options.max_scale_sigma_rel, 6):
            assert scale_sigma_rel * speed <= velocity_sigma_limit(options, speed)
    assert velocity_sigma_limit(options, 8.0) > 0.707  # the landfill's start
    assert velocity_sigma_limit(VisualInertialOptions(max_scale_sigma_rel=0.05), 8.0) < 0.707


def test_the_solver_refuses_windows_that_do_not_determine_it():
    flight = simulate_flight("book", 6.0, 3, SimulationOptions(start_s=20.0))
    init, start = run_start(flight, seconds=1.6)
    frames = init._usable_frames()
    problem, _, _ = init._problem(frames)
    assert acceleration_spread(problem) > 0.25
    solution = solve_window(problem)
    assert 0.0 < scale_sigma(problem, solution) < 0.05
    assert solution.residual_ratio < 1.0 and np.mean(solution.inliers) > 0.95
    assert abs(np.linalg.norm(solution.gravity_dir) - 1.0) < 1e-9
    few = type(problem)(**{**{f: getattr(problem, f) for f in problem.__dataclass_fields__},
                           "obs_frame": problem.obs_frame[:10], "obs_point": np.minimum(problem.obs_point[:10], 4),
                           "obs_xn": problem.obs_xn[:10]})
    with pytest.raises(WindowFailure, match="too few"):
        solve_window(few)


def test_options_are_checked():
    with pytest.raises(ValueError, match="min_window_s"):
        VisualInertialOptions(window_s=1.0, min_window_s=2.0)
    with pytest.raises(ValueError, match="min_points"):
        VisualInertialOptions(min_points=3)
    assert math.isclose(VisualInertialOptions().window_s, 5.0)
