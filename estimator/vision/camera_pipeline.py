"""One camera frame through EKF-SLAM: predict, associate, update, manage the map.

The estimator calls :meth:`CameraPipeline.process` with the state already propagated to the
frame's time. The matches of a frame are fused together: those of landmarks whose depth has
been observed in one stacked EKF update, those whose depth is still a guess in one iterated
EKF update (see :meth:`CameraPipeline._update` for why). The pipeline owns what the filter state does not: the landmarks' ids,
descriptors and match statistics (:class:`~vtolpose.estimator.vision.map_manager.LandmarkBook`, in the
state's landmark order). It returns a :class:`FrameReport` with everything a person needs to
see why the filter did what it did (the per-frame overlay is drawn from it).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from vtolpose.estimator.vision.association import AssociationOptions, associate
from vtolpose.estimator.core.calibration import CameraCalibration
from vtolpose.estimator.vision.camera_model import CameraModel
from vtolpose.estimator.vision.camera_update import (
    Predictions, assign_state, iterated_update, parallax_significance, predict, stacked_update,
)
from vtolpose.estimator.vision.features import FrameFeatures
from vtolpose.estimator.core.kalman import UpdateOutcome
from vtolpose.estimator.vision.landmarks import (
    add_landmarks,
    baseline_significance,
    initial_landmarks,
    landmark_points,
    map_prior_jacobians,
    remove_landmarks,
    world_rays,
)
from vtolpose.estimator.vision.map_manager import (
    LandmarkBook,
    MapOptions,
    deletions,
    depth_known,
    depth_priors,
    record_settling,
    scene_depth,
    select_new_features,
)
from vtolpose.estimator.core.state import FilterState
from vtolpose.estimator.vision.mounting import MountingEstimate, MountingOptions, mounted, new_landmark_columns
from vtolpose.estimator.vision.time_offset import TimeOffsetEstimate, TimeOffsetOptions, at_frame_time, offset_column


@dataclass(frozen=True, slots=True)
class CameraOptions:
    pixel_sigma: float = 1.0  # px, feature position noise (thesis: R_c)
    association: AssociationOptions = field(default_factory=AssociationOptions)
    map: MapOptions = field(default_factory=MapOptions)
    time_offset: TimeOffsetOptions = field(default_factory=TimeOffsetOptions)
    mounting: MountingOptions = field(default_factory=MountingOptions)
    working_width: int = 0  # frames wider than this are seen reduced to it (CameraCalibration.working); 0: as they are


@dataclass(slots=True)
class FrameReport:
    """What one frame did. Pixel arrays are (K, 2); ids are the landmarks' stable ids."""

    t_ns: int
    accepted: bool
    reason: str = ""
    n_features: int = 0
    n_landmarks: int = 0  # in the map after this frame
    predicted_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    predicted_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    gate_px: float = 0.0
    matched_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    matched_features: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    candidates: int = 0  # landmarks predicted in view
    behind_camera: int = 0
    match_rejections: dict[str, int] = field(default_factory=dict)
    new_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    new_features: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    depth_source: str = ""
    deleted: dict[str, int] = field(default_factory=dict)
    nis: float = float("nan")
    timing_ms: dict[str, float] = field(default_factory=dict)  # wall per stage; "cpu": this thread's CPU time in all

    @property
    def n_matches(self) -> int:
        return len(self.matched_ids)


class CameraPipeline:
    """Visual EKF-SLAM for one calibrated camera."""

    def __init__(self, calibration: CameraCalibration, options: CameraOptions | None = None) -> None:
        self.options = options or CameraOptions()
        self.calibration = calibration
        self.camera = CameraModel(calibration)
        self.R_BC = np.asarray(calibration.R_BC, dtype=float)  # as configured: a state may hold a correction
        self.t_BC = np.asarray(calibration.t_BC, dtype=float)  # (vision.mounting.mounted)
        self.book = LandmarkBook()
        self.time_offset = TimeOffsetEstimate(self.options.time_offset)  # what it is while no state holds it
        self.mounting = MountingEstimate(self.options.mounting)  # likewise
        self._rate_b = np.zeros(3)  # the frame's bias-corrected gyro
        self.initialized_total = 0
        self.deleted_total: dict[str, int] = {}

    def attach_calibration(self, state: FilterState) -> None:
        """Give ``state`` the calibration states the options ask for, if it has none (a new or rebuilt state)."""
        self.time_offset.attach(state)
        self.mounting.attach(state)

    def clear(self, state: FilterState) -> int:
        """Forget every landmark (after a filter reset: they belong to the old frame)."""
        n = len(self.book)
        if state.n_landmarks:
            remove_landmarks(state, np.ones(state.n_landmarks, dtype=bool))
        self.book.clear()
        return n

    def adopt(self, state: FilterState, descriptors: np.ndarray, sigma_rho0: np.ndarray) -> None:
        """Take the landmarks already in ``state`` (a visual-inertial start) as the map, with their descriptors."""
        self.book.clear()
        self.book.append(np.asarray(descriptors), np.asarray(sigma_rho0, dtype=float))
        self.initialized_total += state.n_landmarks

    def process(
        self,
        state: FilterState,
        features: FrameFeatures,
        t_ns: int,
        add_allowed: bool,
        absolute_position: bool,
        held: np.ndarray | None = None,
        rate_b: np.ndarray | None = None,
    ) -> FrameReport:
        """Update ``state`` with one frame's features (already at the frame's stamp). ``rate_b``: the latest
        bias-corrected gyro (the pose's turn over an estimated time offset); ``held`` covers the state as it
        is given, so its calibration states are attached (:meth:`attach_calibration`) before."""
        opts = self.options
        clock = time.perf_counter
        t0, cpu0 = clock(), time.thread_time()
        report = FrameReport(t_ns, True, n_features=len(features), gate_px=opts.association.gate_px)
        if len(self.book) != state.n_landmarks:  # the filter was rebuilt under us: start over
            self.clear(state)
        self._rate_b = np.zeros(3) if rate_b is None else np.asarray(rate_b, dtype=float)
        m = state.n_landmarks
        pred = predict(state, self.camera, self.R_BC, self.t_BC, opts.pixel_sigma, self._rate_b) if m else None
        t1 = clock()
        matched = np.zeros(m, dtype=bool)
        in_view = np.zeros(m, dtype=bool)
        in_front = np.ones(m, dtype=bool)
        if pred is not None:
            in_view, in_front = pred.in_image, pred.in_front
            report.predicted_ids = self.book.ids[in_view]
            report.predicted_uv = pred.uv[in_view]
            report.behind_camera = int(np.sum(~in_front))
            assoc = associate(pred, self.book.descriptors, features, opts.association)
            report.candidates = assoc.candidates
            report.match_rejections = dict(assoc.rejected)
        t2 = clock()
        if pred is not None and len(assoc):
            snapshot = state.copy()
            outcome = self._update(state, pred, assoc.landmark, features.keypoints[assoc.feature], held)
            if outcome.accepted and state.is_finite():
                matched[assoc.landmark] = True
                record_settling(self.book, state, assoc.landmark, opts.map)
                report.matched_ids = self.book.ids[assoc.landmark]
                report.matched_features = assoc.feature
                report.nis = outcome.nis
            else:
                assign_state(state, snapshot)
                report.accepted = False
                report.reason = "singular_innovation" if "singular" in outcome.reason else "non_finite_update"
        t3 = clock()
        if m:
            self.book.record(in_view, matched)
            gone = deletions(self.book, state, in_front, opts.map)
            remove = np.zeros(m, dtype=bool)
            for reason, mask in gone.items():
                if np.any(mask):
                    report.deleted[reason] = int(np.sum(mask))
                    self.deleted_total[reason] = self.deleted_total.get(reason, 0) + int(np.sum(mask))
                remove |= mask
            remove_landmarks(state, remove)
            self.book.keep(~remove)
            in_view = in_view[~remove]
        if add_allowed and report.accepted:
            occupied = report.predicted_uv
            if len(report.matched_features):
                occupied = np.vstack([occupied, features.keypoints[report.matched_features]])
            self._add(state, features, in_view, occupied, absolute_position, report)
        report.n_landmarks = state.n_landmarks
        self.time_offset.remember(state)
        self.mounting.remember(state)
        t4 = clock()
        report.timing_ms = {
            "predict": (t1 - t0) * 1e3, "associate": (t2 - t1) * 1e3, "update": (t3 - t2) * 1e3,
            "map": (t4 - t3) * 1e3, "total": (t4 - t0) * 1e3, "cpu": (time.thread_time() - cpu0) * 1e3,
        }
        return report

    def _update(
        self, state: FilterState, pred: Predictions, landmarks: np.ndarray, uv: np.ndarray, held: np.ndarray | None
    ) -> UpdateOutcome:
        """Fuse the frame's matches, in up to three groups by what their landmark's depth is worth.

        The measurement is bilinear in a landmark's inverse depth and the camera centre.
        - Depth observed (:func:`~vtolpose.estimator.vision.map_manager.depth_known`): one stacked EKF update.
        - Depth guessed, camera well away from the anchor: an iterated EKF update. The first real
          baseline can move a guessed depth a long way; one linearisation at the guess gets the
          depth, the robot's correction and both variances wrong (it reads parallax as motion).
        - Depth guessed, no baseline or no parallax yet: such a match still says the camera has
          not moved relative to the scene, so it updates position, velocity and the accelerometer
          bias (on a pad it is a zero-velocity update, and a rest is what tells that bias), the
          landmark's bearing, and, since a turn moves every bearing alike whatever the depth, the
          attitude; its depth and the gyro bias are held (a Schmidt update). Without parallax the
          depth cannot be observed; an apparent baseline that is only position noise (GPS steps
          while the vehicle sits on its pad) or drift would otherwise be "explained" by a bogus
          depth. A held attitude let a hover's gyro-bias error tilt the estimate unseen, and its
          gravity leak grew a velocity error that the first baseline read as parallax. The gyro
          bias stays held: with the depth a guess, a translation's flow can pass for a turn, and a
          bias keeps what it is given (on the hand-held recording, freeing it took the path from
          2.6 × 2.3 m to 14 × 9 m); the attitude is corrected again by every frame. The
          accelerometer bias was held too until these matches needed parallax: then on the
          landfill's pad they pinned the velocity, the rest's zero-velocity updates found nothing
          left to tell the bias (its vertical sigma 0.027 m/s² at lift-off against IMU + GPS's
          0.002), and the climb read the bias's error as a climb rate (0.1 m/s, 0.49 m high).
        """
        opts = self.options
        known = depth_known(self.book, state, landmarks, opts.map)
        baseline = baseline_significance(state, landmarks, mounted(state, self.R_BC, self.t_BC)[1]) >= opts.map.min_baseline_chi2
        if np.any(~known & baseline):
            guessed = np.flatnonzero(~known & baseline)
            parallax = parallax_significance(state, self.camera, self.R_BC, self.t_BC, landmarks[guessed], uv[guessed],
                                             opts.pixel_sigma, self._rate_b) >= opts.map.min_baseline_chi2
            baseline[guessed[~parallax]] = False
        outcome = None
        if np.any(known):
            outcome = stacked_update(state, pred, landmarks[known], uv[known], opts.pixel_sigma, held)
            if not outcome.accepted:
                return outcome
        groups = (
            (~known & baseline, None, opts.map.guessed_iterations),
            (~known & ~baseline, self._no_baseline_held(state, landmarks[~known & ~baseline]), 1),
        )
        for members, extra_held, iterations in groups:
            if not np.any(members):
                continue
            hold = held if extra_held is None else extra_held if held is None else held | extra_held
            step = iterated_update(state, self.camera, self.R_BC, self.t_BC, landmarks[members], uv[members],
                                   opts.pixel_sigma, hold, iterations, self._rate_b)
            if not step.accepted:
                return step
            outcome = step if outcome is None else UpdateOutcome(True, outcome.nis + step.nis, outcome.dof + step.dof)
        return outcome

    @staticmethod
    def _no_baseline_held(state: FilterState, landmarks: np.ndarray) -> np.ndarray:
        """The landmarks' depths, the gyro bias and the calibration states, time offset and mounting (see :meth:`_update`)."""
        hold = np.zeros(state.dim, dtype=bool)
        if state.layout.estimates_biases:
            hold[state.layout.BG] = True
        hold[state.robot_dim : state.map_start] = True
        hold[state.map_start + 6 * landmarks + 5] = True
        return hold

    def _add(self, state: FilterState, features: FrameFeatures, in_view: np.ndarray, occupied: np.ndarray,
             absolute_position: bool, report: FrameReport) -> None:
        mo = self.options.map
        n_new = min(mo.max_new_per_frame, mo.target_in_view - int(np.sum(in_view)), mo.max_landmarks - state.n_landmarks)
        chosen = select_new_features(features, occupied, report.matched_features, n_new, mo.min_feature_distance_px, mo.border_px)
        if len(chosen) == 0:
            return
        at = at_frame_time(state, self._rate_b)  # the pose the frame saw: the state's own without a time offset
        R_BC, t_BC = mounted(state, self.R_BC, self.t_BC)  # the state's estimate, if it holds one
        R_WB = at.R
        R_WC = R_WB @ R_BC
        c_w = at.p + R_WB @ t_BC
        uv = features.keypoints[chosen]
        rays_w, xn = world_rays(R_WB, R_BC, self.camera, uv)
        rays_w /= np.linalg.norm(rays_w, axis=1, keepdims=True)
        rays_c = np.column_stack([xn, np.ones(len(xn))])
        reference = scene_depth(self.book, at, R_WC, c_w, in_view, mo)
        rho0, sigma_rho, source = depth_priors(rays_w, rays_c, c_w, absolute_position,
                                               None if reference is None else reference[0], mo)
        y, J_x, J_z = initial_landmarks(at.p, R_WB, self.camera, R_BC, t_BC, uv, rho0)
        extra_cols = J_extra = None
        if source == "map":
            # The prior is the reference landmark's depth, a function of the state: its error is
            # shared, not new (only the scene's spread, depth_sigma_rel, is independent).
            extra_cols, J_extra = map_prior_jacobians(at, R_WC, c_w, reference[1], rho0, J_x)
        if state.calib.shape[0]:  # placed with the calibration's estimate: the new landmarks share its error
            calib = []
            if state.calib_layout.time_offset:  # placed from the pose at t + t_d
                calib.append(offset_column(J_x, state, self._rate_b))
            if state.calib_layout.mounting:  # from the camera centre and along the ray the mounting gives
                point = None if source != "map" else landmark_points(state.landmarks[reference[1]][None, :])[0]
                calib.append(new_landmark_columns(R_WB, R_BC, rays_c, None if point is None else (point, c_w, rho0)))
            calib_cols = np.arange(state.robot_dim, state.map_start)
            J_calib = np.concatenate(calib, axis=2)
            extra_cols = calib_cols if extra_cols is None else np.concatenate([extra_cols, calib_cols])
            J_extra = J_calib if J_extra is None else np.concatenate([J_extra, J_calib], axis=2)
        px2 = self.options.pixel_sigma**2
        R_z = np.zeros((len(chosen), 3, 3))
        R_z[:, 0, 0] = R_z[:, 1, 1] = px2
        R_z[:, 2, 2] = sigma_rho**2
        add_landmarks(state, y, J_x, J_z, R_z, extra_cols, J_extra)
        report.new_ids = self.book.append(features.descriptors[chosen], sigma_rho)
        report.new_features = chosen
        report.depth_source = source
        self.initialized_total += len(chosen)

