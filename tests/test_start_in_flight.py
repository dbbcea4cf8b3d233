"""A service that starts in the air: no confident nonsense, and a real visual-inertial start.

Rendered flights that begin mid-trajectory (``simulate --start-in-flight``) and recordings joined
later (``run --replay … --start-at``), through the runtime. What must hold: until a start has
converged nothing is published; IMU+camera converges within 10 s or publishes nothing; IMU+GPS has
its heading within 20 s; no usable pose, least of all the last, is further than 5 σ from the truth;
a filter whose innovations say it is lost caps its quality, resets and says why. ORB keeps it fast.
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

pytest.importorskip("skimage", reason="rendering needs scikit-image (the 'sim' extra)")

from vtolpose.config import load_config  # noqa: E402
from vtolpose.drivers.files.dataset import Dataset  # noqa: E402
from vtolpose.drivers.files.tum import read_tum  # noqa: E402
from vtolpose.drivers.simulator import SimulationOptions  # noqa: E402
from vtolpose.estimator.core.rotation import quat_exp, quat_mul  # noqa: E402
from vtolpose.estimator.filter import Estimator  # noqa: E402
from vtolpose.estimator.fusion import FusionCore, FusionOptions, OutputPose  # noqa: E402
from vtolpose.estimator.metrics import nees, pose_errors_for_nees  # noqa: E402
from vtolpose.estimator.status import EventKind  # noqa: E402
from vtolpose.estimator.vision.features import extract_features  # noqa: E402
from vtolpose.estimator.core.measurements import GpsFix, ImuSample  # noqa: E402
from vtolpose.estimator.modes import FilterMode  # noqa: E402
from vtolpose.service.cli import main  # noqa: E402
from vtolpose.service.replay.report import build_report, start_alignment  # noqa: E402
from vtolpose.service.replay.session import replay  # noqa: E402
from vtolpose.service.outputs.mavlink_odometry import odometry_quality  # noqa: E402
from vtolpose.service.outputs.zenoh import pose_status  # noqa: E402
from vtolpose.service.runtime.status import StatusTracker, pose_problem, pose_quality  # noqa: E402
from vtolpose.service.runtime.wiring import feature_options, filter_options  # noqa: E402

ORB = {"features": {"detector": "orb"}}


def rendered(flight_folder, scenario: str, seconds: float, start_s: float, camera: bool = True) -> Dataset:
    return Dataset.open(flight_folder(scenario, seconds, 2, SimulationOptions(start_s=start_s), camera))


@pytest.fixture(scope="module")
def book(flight_folder) -> Dataset:
    """The arm waving from the first sample (20 s into the scenario), camera rendered."""
    return rendered(flight_folder, "book", 14.0, 20.0)


@pytest.fixture(scope="module")
def landfill(flight_folder) -> Dataset:
    """On a survey leg at 8 m/s, 45 m up, 5 s before a turn: a steady cruise at first."""
    return rendered(flight_folder, "landfill", 10.0, 70.0)


def traced(dataset: Dataset, sensors: list[str], start_at_s: float | None = None):
    poses: list[OutputPose] = []
    cfg = load_config(None, ORB)
    result = replay(dataset, cfg, sensors, on_fused=poses.append, start_at_s=start_at_s)
    return result, poses, build_report(result, dataset, cfg)


def sigmas_off(result, dataset: Dataset, poses: list[OutputPose]) -> np.ndarray:
    """Mahalanobis distance from the truth of each usable pose (6 dof), in the frame the run is scored in."""
    truth, point_b = dataset.truth(), dataset.calibration.truth_point_b
    usable = [p for p in poses if pose_quality(p) > 0]
    t = np.array([p.t_ns for p in usable], dtype=np.int64)
    p = np.array([x.p for x in usable])
    q = np.array([x.q for x in usable])
    c = np.array([x.pose_cov for x in usable])
    align = start_alignment(result, truth, point_b)
    if align is not None:
        p, q, c = align.points(p), align.attitudes(q), align.covariances(c)
    err, cov, _ = pose_errors_for_nees(t, p, q, c, truth, point_b)
    return np.sqrt(nees(err, cov))


def first_usable_s(poses: list[OutputPose], t_first: int) -> float | None:
    usable = [p.t_ns for p in poses if pose_quality(p) > 0]
    return None if not usable else (usable[0] - t_first) * 1e-9


def test_imu_camera_in_flight_starts_within_10_s_and_never_says_nonsense(book):
    result, poses, report = traced(book, ["imu", "camera"])
    t_first = int(book.imu().t_ns[0])
    start = first_usable_s(poses, t_first)
    assert start is not None and start <= 10.0
    started = [e.t_ns for e in result.estimator.events if e.kind is EventKind.STARTED]
    assert len(started) == 1 and result.estimator.events[0].kind in (EventKind.INITIALISING, EventKind.STARTED)
    assert poses[0].t_ns >= started[0]  # nothing before the start
    assert any("visual-inertial start" in e.message for e in result.estimator.events)
    assert report["heading_source"] == "own frame (visual-inertial start)"
    assert report["position_reference"]["heading_aligned"] and "heading_note" in report["position_reference"]
    assert report["nees"]["dof"] == 5  # position and tilt: the heading was turned onto the truth's
    assert report["position_rmse_m"] < 0.02 and report["attitude_rmse_deg"] < 1.0
    assert report["nees"]["mean_in_band"]
    off = sigmas_off(result, book, poses)
    assert off[-1] < 5.0 and np.mean(off < 5.0) > 0.99
    assert report["camera"]["matches_per_frame"]["mean"] > 8


def test_imu_camera_in_a_steady_cruise_stays_initialising(landfill):
    """No acceleration, no scale: nothing is published until a start converges, and it is sound after it."""
    result, poses, report = traced(landfill, ["imu", "camera"])
    t_first = int(landfill.imu().t_ns[0])
    start = first_usable_s(poses, t_first)
    first = result.estimator.events[0]
    assert first.kind is EventKind.INITIALISING and "moving" in first.message  # the camera saw it move: no start at rest
    started = [e.t_ns for e in result.estimator.events if e.kind is EventKind.STARTED]
    assert all(p.t_ns >= started[0] for p in poses) if started else not poses
    if start is not None:  # converged in the turn: then it must be right
        assert start <= 10.0 and sigmas_off(result, landfill, poses)[-1] < 5.0
    else:
        assert report.get("no_scores") and result.estimator.status().initialising
        waiting = report["visual_start"]["still_waiting"]  # and it says why, with what it measured
        assert waiting["check"] in ("motion", "scale") and waiting["text"].startswith("initialising: ")


def test_a_gps_heard_while_the_visual_window_fills_gives_the_start(landfill):
    """In a cruise with a camera and no GPS the estimator waits, initialising, with no state; fixes that begin
    then give the moving start a GPS gives (its first second of fixes, the IMU's latest window): one start,
    no visual-inertial start, no reset, nothing published before it, the position placed at the next fix."""
    cal = landfill.calibration
    est = Estimator(cal, filter_options(load_config(None, ORB), cal.imu.noise))
    poses: list[OutputPose] = []
    fusion = FusionCore(est, FusionOptions(delay_s=0.0), on_fused=poses.append)
    options = feature_options(load_config(None, ORB))
    imu, gps = landfill.imu(), landfill.gps()
    t_first = int(imu.t_ns[0])
    t_gps = t_first + 3_500_000_000  # the GPS comes up after the IMU's window has said "moving"
    events = sorted([(int(t), 0, i) for i, t in enumerate(imu.t_ns)] + [(int(t), 1, 0) for t, _ in landfill.camera_frames()
                    if t < t_first + 5_000_000_000] + [(int(t), 2, i) for i, t in enumerate(gps.t_ns) if t >= t_gps])
    frames = dict(landfill.camera_frames())
    modes = []
    for t, kind, i in events:
        if kind == 0:
            fusion.add_imu(ImuSample(t, imu.gyro[i], imu.accel[i]))
        elif kind == 1:
            features = extract_features(landfill.load_frame(frames[t]), t, options, (cal.camera.height, cal.camera.width))
            fusion.add_measurement(t, lambda e, f=features: e.process_features(f), "camera")
        else:
            fix = GpsFix(t, gps.p_ned[i], float(gps.sigma_h[i]), float(gps.sigma_v[i]))
            fusion.add_measurement(t, lambda e, f=fix: e.process_gps(f), "gps")
        if not modes or modes[-1] is not est.mode:
            modes.append(est.mode)
        assert (est.state is None) == (not est.mode.initialised)  # no half-started filter, ever
    fusion.flush()
    assert modes[:4] == [FilterMode.WAITING, FilterMode.INITIALISING, FilterMode.UNREFERENCED, FilterMode.GPS], modes
    kinds = [e.kind for e in est.events]
    assert kinds[:2] == [EventKind.INITIALISING, EventKind.STARTED] and "GPS" in est.events[1].message
    started = est.events[1].t_ns
    assert (started - t_gps) * 1e-9 == pytest.approx(1.0, abs=0.15)  # a second of fixes
    assert est.reset_counter == 0 and kinds.count(EventKind.STARTED) == 1  # no visual-inertial start after it
    assert poses and poses[0].t_ns >= started


@pytest.fixture(scope="module")
def landfill_gps(flight_folder) -> Dataset:
    return rendered(flight_folder, "landfill", 30.0, 70.0, camera=False)


def test_imu_gps_in_a_cruise_never_starts_at_rest_nor_publishes_before_its_heading(landfill_gps):
    """A steady cruise feels still to the IMU; the GPS sees it move, so there is no start at rest (with
    zero velocity and a confident covariance), and nothing usable is published before the heading."""
    result, poses, _ = traced(landfill_gps, ["imu", "gps"])
    assert not any(", still;" in e.message for e in result.estimator.events)
    assert all(pose_quality(p) <= 0 for p in poses if not p.heading_aligned)


@pytest.mark.parametrize("scenario, start_s", [("landfill", 70.0), ("book", 20.0)])
def test_imu_gps_in_flight_has_its_heading_within_20_s_and_stays_within_5_sigma(flight_folder, scenario, start_s):
    dataset = rendered(flight_folder, scenario, 30.0, start_s, camera=False)
    result, poses, _ = traced(dataset, ["imu", "gps"])
    aligned = [p for p in poses if p.heading_aligned]
    assert aligned and (aligned[0].t_ns - int(dataset.imu().t_ns[0])) * 1e-9 <= 20.0  # placed by the heading bank
    assert result.estimator.heading_placement is not None
    assert sigmas_off(result, dataset, poses)[-1] < 5.0  # the flight does not end in confident nonsense


def test_a_lost_filter_caps_its_quality_resets_and_says_why(book, caplog):
    """Turn the attitude 20° and the velocity 0.3 m/s away mid-flight: the camera's innovations leave their
    band, the quality is capped within a second, the filter resets and starts again from the images. While
    the visual-inertial start waits, the status document and the log say why, with what it measured."""
    tracker = StatusTracker()
    waiting: list[dict] = []
    cfg = load_config(None, ORB)
    cal = book.calibration
    est = Estimator(cal, filter_options(cfg, cal.imu.noise))
    poses: list[OutputPose] = []
    fusion = FusionCore(est, FusionOptions(delay_s=0.0), on_fused=poses.append)
    options = feature_options(cfg)
    frames = {t: path for t, path in book.camera_frames()}
    imu = book.imu()
    t_first = int(imu.t_ns[0])
    kick_ns = t_first + 4_000_000_000
    out_of_band_since: int | None = None
    kicked = False
    events = sorted([(int(t), 0, i) for i, t in enumerate(imu.t_ns)] + [(t, 1, 0) for t in frames])
    for t, kind, i in events:
        if kind == 0:
            fusion.add_imu(ImuSample(t, imu.gyro[i], imu.accel[i]))
        else:
            features = extract_features(book.load_frame(frames[t]), t, options, (cal.camera.height, cal.camera.width))
            fusion.add_measurement(t, lambda e, f=features: e.process_features(f), "camera")
        if not waiting and not est.mode.initialised and est.visual_inertial.progress is not None:
            with caplog.at_level(logging.INFO, logger="vtolpose.service.runtime.status"):
                waiting.append(tracker.snapshot(est, fusion))
        if not kicked and est.state is not None and t >= kick_ns:
            est.state.q = quat_mul(quat_exp(np.radians([0.0, 5.0, 20.0])), est.state.q)
            est.state.v = est.state.v + np.array([0.3, 0.0, 0.0])
            kicked = True
        out = est.health.out_of_band(est.state.t_ns) if est.state is not None else []
        if not out:
            out_of_band_since = None
            continue
        if out_of_band_since is None:
            out_of_band_since = est.state.t_ns
        if est.state.t_ns - out_of_band_since >= 1_000_000_000:
            assert all(pose_quality(p) <= 50 for p in poses if p.t_ns >= est.state.t_ns - 10_000_000)
    fusion.flush()
    said = waiting[0]["visual_start"]
    assert said["text"].startswith("initialising: ") and said["check"] in ("window", "tracks", "motion", "scale")
    assert any(m.startswith("visual-inertial start waiting: initialising: ") for m in caplog.messages)
    assert "visual_start" not in tracker.snapshot(est, fusion)  # started (again): nothing waits
    resets = [r for r in est.health.resets if r.kind == "camera_lost"]
    assert kicked and len(resets) == 1 and resets[0].t_ns > kick_ns
    assert "re-observed" in resets[0].reason or "churn" in resets[0].reason or "NIS" in resets[0].reason
    assert (resets[0].t_ns - kick_ns) * 1e-9 < 5.0
    restarts = [e.t_ns for e in est.events if "visual-inertial start" in e.message and e.t_ns > resets[0].t_ns]
    assert restarts, "the visual-inertial start did not run again after the reset"
    assert poses[-1].reset_counter == 1 and pose_quality(poses[-1]) > 50  # back, and says so through the counter
    dropped = [p for p in poses if resets[0].t_ns < p.t_ns < restarts[0]]
    assert not dropped  # nothing published between the filter dropped and the visual start again
    capped = [p for p in poses if resets[0].t_ns - 2_000_000_000 <= p.t_ns < resets[0].t_ns]
    assert capped and max(pose_quality(p) for p in capped[-5:]) <= 50


def test_the_daemon_restarted_mid_flight_with_and_without_gps(book, tmp_path, capsys):
    """``run --replay D --start-at S``: the runtime sees nothing before S; camera only, it waits for the
    visual-inertial start; with GPS, for the heading bank. Neither publishes a usable pose before."""
    start_at = 4.0
    t_join = int(book.imu().t_ns[0]) + int(start_at * 1e9)
    for sensors in ("imu,camera", "imu,camera,gps"):
        traj = tmp_path / f"{sensors}.txt"
        assert main(["run", "--replay", str(book.root), "--start-at", str(start_at), "--sensors", sensors,
                     "--set", "features.detector=orb", "--out", str(traj)]) == 0
        t, _, _ = read_tum(traj)
        assert len(t) > 100 and t[0] * 1e9 >= t_join - 1
    capsys.readouterr()
    for sensors in (["imu", "camera"], ["imu", "camera", "gps"]):
        result, poses, report = traced(book, sensors, start_at_s=start_at)
        assert poses[0].t_ns >= t_join
        start = first_usable_s(poses, t_join)
        assert start is not None and start <= (10.0 if "gps" not in sensors else 20.0)
        assert all(pose_quality(p) <= 0 for p in poses if (p.t_ns - t_join) * 1e-9 < start)
        assert report["heading_source"] != "known"  # the recording's stated heading was not used
        assert sigmas_off(result, book, poses)[-1] < 5.0
    report_path = tmp_path / "r.json"
    assert main(["replay", str(book.root), "--start-at", str(start_at), "--sensors", "imu,camera", "--set",
                 "features.detector=orb", "--no-progress", "--report", str(report_path)]) == 0
    assert json.loads(report_path.read_text())["position_reference"]["kind"] == "start"
    assert main(["run", "--start-at", "3", "--duration", "1"]) == 2
    assert "use it with --replay" in capsys.readouterr().err
    assert main(["run", "--replay", str(book.root), "--start-at", "99", "--sensors", "imu"]) == 1
    assert "outside the recording" in capsys.readouterr().err


def test_quality_is_minus_one_without_a_position_and_counts_a_camera_only_frame():
    import dataclasses

    pose = OutputPose(0, np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3), np.eye(9) * 1e-6,
                      np.eye(6) * 1e-6, np.zeros(3), True, False, 0, 0)
    assert pose_problem(pose) == "no position" and odometry_quality(pose) == -1  # no position at all
    own = dataclasses.replace(pose, local_position=True)
    assert pose_problem(own) is None and odometry_quality(own) == 100  # the camera's own frame
    # ... its heading too, when none was known: the frame's own, not "not aligned"
    assert pose_problem(dataclasses.replace(own, heading_aligned=False)) is None
    unaligned = dataclasses.replace(pose, position_initialized=True, heading_aligned=False)
    assert pose_problem(unaligned) == "heading not aligned" and odometry_quality(unaligned) == -1
    assert pose_status(pose, pose_quality(pose)) == "no_position" and pose_status(unaligned, 0) == "heading_unaligned"
