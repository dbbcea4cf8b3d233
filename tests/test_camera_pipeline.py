"""Camera frames through the estimator: bad frames, map management, degenerate geometry — counted, never NaN."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vtolpose.estimator.core.covariance import YAW
from vtolpose.estimator.core.calibration import Calibration, CameraCalibration, ImuCalibration, ImuNoise
from vtolpose.estimator.vision.camera_pipeline import CameraOptions, CameraPipeline
from vtolpose.estimator.vision.features import FeatureOptions, FrameFeatures, extract_features
from vtolpose.estimator.filter import Estimator, FilterOptions
from vtolpose.estimator.init.visual_inertial import VisualInertialOptions
from vtolpose.estimator.vision.map_manager import LandmarkBook, MapOptions, deletions, depth_priors, select_new_features
from vtolpose.estimator.core.measurements import GpsFix
from vtolpose.estimator.core.rotation import yaw_of, quat_from_euler
from vtolpose.estimator.core.state import FilterState, StateLayout

R_BC = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
CAM = CameraCalibration(656, 494, 570.0, 570.0, 327.5, 246.5, np.array([-0.12, 0.05, 5e-4, -3e-4, 0.0]), R_BC, np.array([0.05, 0.0, 0.05]))
EPOCH = 1_000_000_000


def textured(seed: int = 0, shape=(494, 656)) -> np.ndarray:
    """A random blob texture: plenty of corners and blobs for any detector."""
    import cv2

    rng = np.random.default_rng(seed)
    noise = rng.normal(size=(shape[0] // 4, shape[1] // 4)).astype(np.float32)
    img = cv2.resize(noise, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    img = 128 + 40 * img / img.std()
    return np.clip(img, 0, 255).astype(np.uint8)


def started_estimator(options: FilterOptions | None = None) -> Estimator:
    cal = Calibration(imu=ImuCalibration(125.0, ImuNoise.isotropic(3e-4, 2e-5, 2e-3, 3e-4)), camera=CAM, initial_heading_rad=0.3)
    est = Estimator(cal, options)
    for k in range(320):  # 2.5 s at rest: the static start
        est.process_imu(EPOCH + k * 8_000_000, np.zeros(3), np.array([0.0, 0.0, -9.80665]))
    assert est.initialized and est.heading_aligned
    return est


def features_at(t_ns: int, uv: np.ndarray, descriptors: np.ndarray) -> FrameFeatures:
    return FrameFeatures(t_ns, np.asarray(uv, float), descriptors, np.arange(len(uv), 0, -1, dtype=float), (494, 656),
                         digest=t_ns.to_bytes(8, "little"))


def grid_uv(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.linspace(60, 596, 8), np.linspace(50, 444, 6))
    uv = np.column_stack([gx.ravel(), gy.ravel()])[:n]
    return uv + rng.uniform(-3, 3, size=uv.shape)


def unit_rows(n: int, seed: int) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 128)).astype(np.float32)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


# ------------------------------------------------------------------------------ bad frames
@pytest.mark.parametrize(
    "image, reason",
    [
        (np.zeros((494, 656), np.uint8), "black"),
        (np.full((494, 656), 255, np.uint8), "saturated"),
        (np.clip(128 + np.random.default_rng(0).normal(0, 3, (494, 656)), 0, 255).astype(np.uint8), "textureless"),
        (np.zeros((480, 640), np.uint8), "wrong_size"),
        (np.zeros((494, 656, 3), np.uint8), "wrong_size"),
    ],
)
def test_bad_frames_are_flagged_before_extraction_and_counted(image, reason):
    features = extract_features(image, EPOCH + 3_000_000_000, FeatureOptions(), expected_shape=(494, 656))
    assert features.problem == reason and len(features) == 0
    est = started_estimator()
    report = est.process_features(features)
    assert not report.accepted and report.reason == reason
    assert est.counts["camera"].rejected == {reason: 1} and est.counts["camera"].used == 0
    assert est.state.is_finite() and est.state.n_landmarks == 0


def test_good_frame_wrong_size_for_the_calibration_is_rejected():
    small = textured(1, (240, 320))
    features = extract_features(small, EPOCH + 3_000_000_000, FeatureOptions())  # no expected shape given here
    assert features.problem is None and len(features) > 50
    est = started_estimator()
    assert est.process_features(features).reason == "wrong_size"


@pytest.mark.parametrize("detector", ["sift", "orb"])
def test_duplicate_and_out_of_order_frames(detector):
    est = started_estimator()
    image = textured(2)
    opts = FeatureOptions(detector=detector, max_features=150)
    first = extract_features(image, EPOCH + 3_000_000_000, opts)
    assert len(first) == 150 and first.binary == (detector == "orb")
    assert np.all(np.diff(first.responses) <= 0)  # strongest first
    assert est.process_features(first).accepted
    assert est.state.n_landmarks > 0
    same_pixels = dataclasses.replace(first, t_ns=EPOCH + 3_133_333_333)
    assert est.process_features(same_pixels).reason == "duplicate"
    older = extract_features(textured(3), EPOCH + 2_900_000_000, opts)
    assert est.process_features(older).reason == "out_of_order"
    assert est.counts["camera"].as_dict() == {"received": 3, "used": 1, "rejected": {"duplicate": 1, "out_of_order": 1}}
    assert est.state.is_finite()


def test_frames_before_the_filter_starts_are_counted():
    """Before the start a frame goes to the visual-inertial start (it may be moving); without it, it waits."""
    cal = Calibration(imu=ImuCalibration(125.0, ImuNoise.isotropic(3e-4, 2e-5, 2e-3, 3e-4)), camera=CAM)
    frame = extract_features(textured(4), EPOCH, FeatureOptions(max_features=50))
    est = Estimator(cal)
    report = est.process_features(frame)
    assert report.reason == "initialising" and est.counts["camera"].rejected == {"initialising": 1}
    assert len(est.visual_inertial.tracker.frames) == 1
    plain = Estimator(cal, FilterOptions(visual_inertial=VisualInertialOptions(enabled=False)))
    report = plain.process_features(frame)
    assert report.reason == "before_start" and plain.counts["camera"].rejected == {"before_start": 1}


def test_unknown_heading_maps_in_the_frame_of_arbitrary_yaw():
    """Before the heading is known the camera maps in the filter's own frame (its yaw a gauge it does not
    touch). Without any GPS that frame is what the outputs publish: the heading the filter started with,
    its variance the drift since; once a GPS is heard they say the heading is unknown in the world."""
    cal = Calibration(imu=ImuCalibration(125.0, ImuNoise.isotropic(3e-4, 2e-5, 2e-3, 3e-4)), camera=CAM)
    est = Estimator(cal)  # no initial heading, no GPS: the heading stays unknown
    for k in range(320):
        est.process_imu(EPOCH + k * 8_000_000, np.zeros(3), np.array([0.0, 0.0, -9.80665]))
    assert est.initialized and not est.heading_aligned
    yaw = yaw_of(est.state.q)
    for k, t_ns in enumerate((3_000_000_000, 3_133_333_333)):
        assert est.process_features(extract_features(textured(5 + k), EPOCH + t_ns, FeatureOptions())).accepted
    assert est.state.n_landmarks > 0 and yaw_of(est.state.q) == pytest.approx(yaw, abs=1e-12)
    assert est.local_position and est.published_cov9()[YAW, YAW] < np.radians(5.0) ** 2
    est.process_gps(GpsFix(EPOCH + 3_200_000_000, np.zeros(3), 0.02, 0.03))
    assert not est.local_position and est.published_cov9()[YAW, YAW] == pytest.approx(np.pi**2 / 3)


# --------------------------------------------------------------------------- map management
def scene_pipeline(options: CameraOptions, n: int = 20) -> tuple[FilterState, CameraPipeline, np.ndarray]:
    """A state looking down from 2 m with ``n`` landmarks born from one frame; their descriptors."""
    state = FilterState(StateLayout("biases"))
    state.t_ns = EPOCH
    state.p = np.array([0.0, 0.0, -2.0])
    state.q = quat_from_euler(0.02, -0.03, 0.4)
    state.cov = np.eye(15) * 1e-6
    birth = dataclasses.replace(options.map, target_in_view=100, max_new_per_frame=100)
    pipe = CameraPipeline(CAM, dataclasses.replace(options, map=birth))
    desc = unit_rows(n, 7)
    report = pipe.process(state, features_at(EPOCH, grid_uv(n), desc), EPOCH, True, True)
    assert 0 < len(report.new_ids) == state.n_landmarks == len(pipe.book)
    pipe.options = options
    return state, pipe, desc


def seen(pipe: CameraPipeline, state: FilterState, desc: np.ndarray, which: np.ndarray, t_ns: int) -> FrameFeatures:
    """Features exactly at the predicted pixels of landmarks ``which`` (by row), with their descriptors."""
    from vtolpose.estimator.vision.camera_update import predict

    uv = predict(state, pipe.camera, pipe.R_BC, pipe.t_BC, 1.0).uv
    row_of = {int(i): r for r, i in enumerate(pipe.book.ids)}
    rows = [row_of[i] for i in which if int(i) in row_of]
    return features_at(t_ns, uv[rows], pipe.book.descriptors[rows])


def test_stale_landmarks_are_deleted_with_their_rows_and_columns():
    opts = CameraOptions(map=MapOptions(stale_frames=3, target_in_view=0, max_landmarks=40))
    state, pipe, desc = scene_pipeline(opts, 20)
    ids = pipe.book.ids.copy()
    keep = ids[:12]  # the other 8 are in view but never matched again
    deleted = {}
    for k in range(1, 4):
        report = pipe.process(state, seen(pipe, state, desc, keep, EPOCH + k), EPOCH + k, False, True)
        assert report.accepted and report.n_matches == 12
        for reason, n in report.deleted.items():
            deleted[reason] = deleted.get(reason, 0) + n
    assert deleted == {"stale": 8}
    assert sorted(pipe.book.ids.tolist()) == sorted(keep.tolist())
    assert state.n_landmarks == 12 and state.cov.shape == (15 + 72, 15 + 72)
    assert state.is_finite() and np.allclose(state.cov, state.cov.T)


def test_the_map_is_capped_and_new_landmarks_are_spread_out():
    opts = CameraOptions(map=MapOptions(max_landmarks=15, max_new_per_frame=40, target_in_view=40, min_feature_distance_px=30.0))
    state, pipe, _ = scene_pipeline(opts, 30)
    assert state.n_landmarks == 15  # capped at birth
    uv = grid_uv(30)[:15]
    d = np.linalg.norm(uv[:, None] - uv[None], axis=2) + np.eye(15) * 1e9
    assert d.min() >= 30.0


def test_select_new_features_keeps_distance_border_and_strength_order():
    kp = np.array([[5.0, 100.0], [100.0, 100.0], [110.0, 100.0], [300.0, 200.0], [305.0, 300.0], [400.0, 400.0]])
    feats = features_at(1, kp, unit_rows(6, 1))
    chosen = select_new_features(feats, np.array([[400.0, 390.0]]), np.array([4]), 10, 30.0, 12.0)
    # 0: at the border; 2: too close to 1; 4: already matched; 5: near an existing landmark.
    assert chosen.tolist() == [1, 3]
    assert select_new_features(feats, np.zeros((0, 2)), np.zeros(0, int), 1, 30.0, 12.0).tolist() == [1]


def test_deletion_reasons_from_the_book():
    book = LandmarkBook()
    book.append(unit_rows(4, 2), np.full(4, 0.5))
    state = FilterState(StateLayout("thesis"))
    state.landmarks = np.ones((4, 6))
    opts = MapOptions(stale_frames=2, out_of_view_frames=2, min_match_ratio=0.5, min_predictions_for_ratio=4)
    for _ in range(2):
        book.record(np.array([True, True, False, True]), np.array([True, False, False, True]))
    book.record(np.array([True, True, False, True]), np.array([True, True, False, False]))
    book.record(np.array([True, True, False, True]), np.array([False, True, False, False]))
    gone = deletions(book, state, np.array([True, True, False, True]), opts)
    # 0: matched 3 of 4; 1: 2 of 4 (ratio 0.5 is enough); 2: never in view and behind; 3: 2 misses in a row.
    assert [np.flatnonzero(gone[r]).tolist() for r in ("behind_camera", "stale", "out_of_view", "match_ratio")] == [[2], [3], [], []]
    state.landmarks[0, 5] = np.nan
    assert deletions(book, state, np.ones(4, bool), opts)["non_finite"].tolist() == [True, False, False, False]


def test_depth_priors_prefer_height_then_map_then_civera():
    opts = MapOptions(rho0=0.1, sigma_rho=0.5, depth_sigma_rel=0.5, ground_down_m=0.0)
    rays_w = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [1.0, 0.0, 0.0]])
    rays_c = np.array([[0.0, 0.0, 1.0], [0.75, 0.0, 1.0], [0.0, 0.0, 1.0]])
    rho, sigma, source = depth_priors(rays_w, rays_c, np.array([0.0, 0.0, -40.0]), True, 5.0, opts)
    assert source == "height"
    np.testing.assert_allclose(rho[:2], [1 / 40.0, 0.8 / 40.0])
    assert rho[2] == 0.1 and sigma[2] == 0.5  # a horizontal ray never meets the ground
    rho, sigma, source = depth_priors(rays_w, rays_c, np.array([0.0, 0.0, -40.0]), False, 5.0, opts)
    assert source == "map"
    np.testing.assert_allclose(rho[:2], [1 / 5.0, 1 / 6.25])
    np.testing.assert_allclose(sigma, 0.5 * rho)
    rho, sigma, source = depth_priors(rays_w, rays_c, np.zeros(3), False, None, opts)
    assert source == "civera" and np.all(rho == 0.1) and np.all(sigma == 0.5)


# ------------------------------------------------------------------ degenerate geometry
def test_landmark_behind_the_camera_is_counted_then_deleted_never_nan():
    est = started_estimator(FilterOptions(camera=CameraOptions(map=MapOptions(out_of_view_frames=2))))
    first = extract_features(textured(6), EPOCH + 3_000_000_000, FeatureOptions(max_features=80))
    est.process_features(first)
    state = est.state
    behind_id = int(est.camera.book.ids[0])
    state.landmarks[0, 3:6] = [np.pi, 0.0, 0.5]  # a point 2 m straight *up* from its anchor
    reports = [est.process_features(extract_features(textured(7 + k), EPOCH + 3_200_000_000 + k * 133_333_333,
                                                     FeatureOptions(max_features=80))) for k in range(2)]
    assert reports[0].behind_camera == 1 and est.counts["camera_match"].flagged["behind_camera"] >= 1
    assert reports[1].deleted.get("behind_camera") == 1
    assert behind_id not in est.camera.book.ids
    assert est.state.is_finite() and np.all(np.isfinite(est.state.landmarks))


def test_singular_innovation_covariances_are_rejected_and_the_state_kept():
    # Individually singular: no pixel noise and no uncertainty at all.
    state, pipe, desc = scene_pipeline(CameraOptions(pixel_sigma=0.0, map=MapOptions(target_in_view=0)), 6)
    state.cov[:] = 0.0
    report = pipe.process(state, seen(pipe, state, desc, pipe.book.ids, EPOCH + 1), EPOCH + 1, False, True)
    assert report.match_rejections == {"singular_S": 6} and report.n_matches == 0
    # Jointly singular: each 2 x 2 S is fine, the stacked one has rank 2 (only two uncertain states).
    state.cov[0, 0] = state.cov[1, 1] = 1e-4
    before = state.copy()
    report = pipe.process(state, seen(pipe, state, desc, pipe.book.ids, EPOCH + 2), EPOCH + 2, False, True)
    assert not report.accepted and report.reason == "singular_innovation"
    np.testing.assert_array_equal(state.cov, before.cov)
    np.testing.assert_array_equal(state.p, before.p)
    assert state.is_finite()


# ------------------------------------------------------------------ guessed vs known depth
def test_a_guessed_depth_is_held_until_the_camera_has_moved():
    state, pipe, desc = scene_pipeline(CameraOptions(map=MapOptions(target_in_view=0)), 8)
    frame = seen(pipe, state, desc, pipe.book.ids, EPOCH + 1)
    shifted = dataclasses.replace(frame, keypoints=frame.keypoints + np.array([1.5, -1.0]))
    before = state.copy()
    assert pipe.process(state, shifted, EPOCH + 1, False, True).n_matches == 8  # no baseline yet
    np.testing.assert_array_equal(state.landmarks[:, 5], before.landmarks[:, 5])
    assert np.abs(state.landmarks[:, 3:5] - before.landmarks[:, 3:5]).max() > 1e-5  # bearings do move
    # 30 cm away (known to 1 mm), the landmarks really 2 m deep: now the depths move towards the truth.
    truth = state.landmarks.copy()
    truth[:, 5] = 0.5
    state.p = state.p + np.array([0.3, 0.0, 0.0])
    state.cov[0:3, 0:3] += np.eye(3) * 1e-6
    real = state.copy()
    real.landmarks = truth
    from vtolpose.estimator.vision.camera_update import predict

    uv = predict(real, pipe.camera, pipe.R_BC, pipe.t_BC, 1.0).uv
    order = {int(i): r for r, i in enumerate(pipe.book.ids)}
    rows = [order[int(i)] for i in pipe.book.ids]
    moved = features_at(EPOCH + 2, uv[rows], pipe.book.descriptors[rows])
    rho_before = state.landmarks[:, 5].copy()
    assert pipe.process(state, moved, EPOCH + 2, False, True).n_matches == 8
    assert np.all(np.abs(state.landmarks[:, 5] - 0.5) < 0.5 * np.abs(rho_before - 0.5))


def test_baseline_significance_grows_with_the_displacement_since_the_anchor():
    from vtolpose.estimator.vision.landmarks import baseline_significance

    state, pipe, _ = scene_pipeline(CameraOptions(), 4)
    assert np.all(baseline_significance(state, np.arange(4), CAM.t_BC) < 1e-6)  # seen from where they were born
    state.cov[0:3, 0:3] += np.eye(3) * 0.01**2  # 1 cm of new position uncertainty, then a 5 cm move
    state.p = state.p + np.array([0.05, 0.0, 0.0])
    np.testing.assert_allclose(baseline_significance(state, np.arange(4), CAM.t_BC), 25.0, rtol=0.05)


def test_detector_choice_and_a_missing_akaze_are_explicit():
    import cv2

    with pytest.raises(ValueError, match="unknown feature detector 'surf'"):
        FeatureOptions(detector="surf")
    if hasattr(cv2, "AKAZE_create"):
        assert len(extract_features(textured(8), 0, FeatureOptions(detector="akaze"))) > 0
    else:
        with pytest.raises(ValueError, match="'akaze' is not in this OpenCV build"):
            FeatureOptions(detector="akaze")


def test_frames_without_a_camera_calibration_are_counted():
    cal = Calibration(imu=ImuCalibration(125.0, ImuNoise.isotropic(3e-4, 2e-5, 2e-3, 3e-4)))
    est = Estimator(cal)
    assert est.process_features(extract_features(textured(9), EPOCH, FeatureOptions(max_features=20))).reason == "no_camera_calibration"
    assert est.counts["camera"].rejected == {"no_camera_calibration": 1}


def test_select_new_features_spaces_them_as_the_pairwise_distances_say():
    """Hundreds of features against dozens of occupied pixels: the choice is the greedy rule written out with every
    pairwise distance (free of the border, the used features and the occupied pixels by the limit, strongest first)."""
    rng = np.random.default_rng(7)
    kp = np.column_stack([rng.uniform(0, 656, 400), rng.uniform(0, 494, 400)])
    feats = features_at(1, kp, unit_rows(400, 2))
    occupied = np.column_stack([rng.uniform(0, 656, 40), rng.uniform(0, 494, 40)])
    occupied[3] = np.nan  # a prediction behind the camera occupies nothing
    used = rng.choice(400, 30, replace=False)
    chosen = select_new_features(feats, occupied, used, 25, 30.0, 12.0)
    expected: list[int] = []
    near = np.nanmin(np.linalg.norm(kp[:, None] - occupied[None], axis=2), axis=1)
    for i in range(400):
        inside = 12.0 <= kp[i, 0] <= 655 - 12.0 and 12.0 <= kp[i, 1] <= 493 - 12.0
        if i in used or not inside or near[i] < 30.0:
            continue
        if expected and np.min(np.linalg.norm(kp[expected] - kp[i], axis=1)) < 30.0:
            continue
        expected.append(i)
        if len(expected) == 25:
            break
    assert len(expected) >= 10
    assert chosen.tolist() == expected
