"""The visual-inertial start: when a window of tracks and IMU deltas has converged, the EKF-SLAM's first state.

:class:`VisualInertialInitializer` buffers the filter's IMU deltas and tracks the camera's
features; from ``min_window_s`` of frames on it solves the last ``window_s``
(:mod:`~vtolpose.estimator.init.window_solver`) at every frame. A solution is accepted only
when its residuals match the noise, gravity's direction, the velocity and the scale (the
relative depth of the points) are well determined, and it has done so on two frames in a row.
Then it becomes a :class:`VisualInertialStart`: the state at the last frame in a world frame
levelled by the solved gravity, its covariance the window's (mapped through the first-order
change of variables, so every correlation between the vehicle and its landmarks stays), and
landmarks for the points seen in the last frame, with their descriptors.

Position and heading are not observable from a camera and an IMU: they are the frame's gauge,
set to what the caller gives (the filter's last position and heading, or a known heading with
its sigma) with a small variance.

When the filter estimates the camera's time offset, the window solves it too, from the same prior,
and the start hands it over with its correlations: a window solved with a wrong configured offset
bends its state to fit it, and a filter whose offset state joins later, uncorrelated, cannot undo
that bend; it reads the bent state as the truth and keeps most of the wrong offset.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from vtolpose.estimator.core.calibration import CameraCalibration, ImuNoise
from vtolpose.estimator.core.rotation import euler_from_quat, rot_to_quat, so3_exp, so3_log
from vtolpose.estimator.core import covariance
from vtolpose.estimator.core.covariance import V
from vtolpose.estimator.core.state import LANDMARK_DIM
from vtolpose.estimator.inertial.imu_delta import ImuDelta
from vtolpose.estimator.inertial.motion_alignment import integrate
from vtolpose.estimator.init.tracks import FeatureTracker, TrackedFrame, TrackOptions
from vtolpose.estimator.init.window_solver import (
    Layout,
    WindowFailure,
    WindowProblem,
    WindowSolution,
    acceleration_spread,
    scale_sigma,
    solve_window,
    tangent_basis,
)
from vtolpose.estimator.vision.association import AssociationOptions
from vtolpose.estimator.vision.camera_model import CameraModel
from vtolpose.estimator.vision.features import FrameFeatures
from vtolpose.estimator.vision.landmarks import INVERSE_DEPTH, angles

ROBOT_DIM = 15


@dataclass(frozen=True, slots=True)
class VisualInertialOptions:
    enabled: bool = True
    window_s: float = 5.0  # the last (up to) this many seconds of frames are solved
    max_frames: int = 16  # frames of the window used, spread evenly over it (the solve grows with their number)
    min_window_s: float = 1.0  # no attempt before the frames span this long
    solve_every_s: float = 0.5  # at most this often (each solve costs tens of milliseconds)
    min_observations: int = 3  # frames a point must be tracked in
    min_frame_rays: int = 8  # a frame with fewer tracked points is left out
    min_points: int = 20
    max_points: int = 80  # tracks taken into the solve, which grows with their number
    max_gravity_error: float = 0.1  # |g| of the linear guess within this fraction of gravity: scale observable
    max_residual_ratio: float = 2.0  # RMS whitened residual: the model fits the measurements
    max_tilt_sigma_deg: float = 1.5  # gravity's direction, from the window's information
    max_scale_sigma_rel: float = 0.25  # the scale, from the window's information (a steady cruise leaves it wide)
    max_velocity_sigma: float = 0.1  # m/s, plus max_scale_sigma_rel of the speed (a speed is known no better than the scale)
    max_depth_sigma_rel: float = 0.25  # median σ_ρ/ρ of the landmarks handed over (the EKF carries the rest)
    min_landmarks: int = 10
    max_landmarks: int = 30  # handed to the EKF (seen in the last frame, best depth first)
    still_flow_px: float = 2.0  # features moving more than this between frames, or over the window: not at rest,
    still_window_s: float = 2.0  # (a steady cruise feels still to the IMU) over the IMU's still window
    position_sigma_m: float = 0.002  # gauge: the frame's origin
    heading_sigma_deg: float = 0.01  # gauge: the frame's heading, when no heading is known
    tracks: TrackOptions = field(default_factory=TrackOptions)

    def __post_init__(self) -> None:
        if not (0.0 < self.min_window_s <= self.window_s):
            raise ValueError(f"visual-inertial start: need 0 < min_window_s <= window_s, got {self.min_window_s}, {self.window_s}")
        if self.min_points < 6 or self.min_landmarks < 1 or self.max_landmarks < self.min_landmarks:
            raise ValueError("visual-inertial start: min_points >= 6 and 1 <= min_landmarks <= max_landmarks")


@dataclass(frozen=True, slots=True)
class VisualInertialStart:
    """The EKF-SLAM's first state: robot ``[p, v, q, b_g, b_a]``, landmarks, the joint covariance."""

    t_ns: int
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    b_g: np.ndarray
    b_a: np.ndarray
    landmarks: np.ndarray  # (L, 6) inverse depth, anchored at the camera of the last frame
    cov: np.ndarray  # (15 [+ 1] + 6L) over [δp, δv, δθ, δb_g, δb_a, (δt_d when solved), δy...]
    descriptors: np.ndarray
    binary: bool
    window_s: float
    n_frames: int
    n_points: int
    residual_ratio: float
    sigma_tilt_deg: float
    sigma_scale_rel: float
    sigma_velocity: float
    depth_sigma_rel: float
    time_offset_s: float | None = None  # the camera's residual time offset, when solved (then in cov after the robot)

    def describe(self) -> str:
        return (f"visual-inertial start from {self.n_frames} frames over {self.window_s:.1f} s, {self.n_points} tracked "
                f"points, {len(self.landmarks)} landmarks: tilt sigma {self.sigma_tilt_deg:.2f} deg, scale sigma "
                f"{100 * self.sigma_scale_rel:.1f} %, velocity sigma "
                f"{self.sigma_velocity:.3f} m/s, depth sigma {100 * self.depth_sigma_rel:.1f} %, residuals "
                f"{self.residual_ratio:.2f}x the noise")


@dataclass(frozen=True, slots=True)
class VisualStartProgress:
    """Why the visual-inertial start has not started yet, with what its last attempt measured.

    ``check`` names the test that failed in one word (``window``, ``tracks``, ``motion``,
    ``residuals``, ``gravity``, ``scale``, ``velocity``, ``landmarks``, ``depth``,
    ``information``, or ``confirming`` while a passed window waits for the next to agree); the
    figures are None where the attempt stopped before measuring them."""

    t_ns: int
    check: str
    reason: str
    attempts: int
    frames: int = 0
    window_s: float = 0.0
    tracks: int = 0  # points tracked over the window's frames, taken into the solve
    excitation: float | None = None  # m/s², RMS of the acceleration about its mean over the window
    scale_sigma_rel: float | None = None
    gravity_sigma_deg: float | None = None
    depth_sigma_rel: float | None = None

    def describe(self) -> str:
        """One ASCII line (a STATUSTEXT carries no more) for a log or an operator, e.g.
        ``initialising: 0.14 m/s^2 RMS over 5.0 s, scale sigma 40 %, ..., <reason>``."""
        parts = []
        if self.excitation is not None:
            parts.append(f"{self.excitation:.2f} m/s^2 RMS over {self.window_s:.1f} s")
        elif self.frames:
            parts.append(f"{self.frames} frames over {self.window_s:.1f} s")
        if self.scale_sigma_rel is not None:
            parts.append(f"scale sigma {100 * self.scale_sigma_rel:.0f} %")
        if self.gravity_sigma_deg is not None:
            parts.append(f"gravity sigma {self.gravity_sigma_deg:.1f} deg")
        if self.depth_sigma_rel is not None:
            parts.append(f"depth sigma {100 * self.depth_sigma_rel:.0f} %")
        if self.tracks:
            parts.append(f"{self.tracks} tracks")
        return "initialising: " + ", ".join(parts + [self.reason])

    def as_dict(self) -> dict:
        def r(x: float | None, digits: int) -> float | None:
            return None if x is None or not math.isfinite(x) else round(float(x), digits)
        return {"check": self.check, "reason": self.reason, "attempts": self.attempts, "frames": self.frames,
                "window_s": round(self.window_s, 3), "tracks": self.tracks, "excitation_m_s2": r(self.excitation, 3),
                "scale_sigma_rel": r(self.scale_sigma_rel, 4), "gravity_sigma_deg": r(self.gravity_sigma_deg, 3),
                "depth_sigma_rel": r(self.depth_sigma_rel, 4), "text": self.describe()}


@dataclass(frozen=True, slots=True)
class Gauge:
    """What the start cannot observe: the world position and heading of the vehicle at the last frame."""

    p: np.ndarray
    heading_rad: float
    heading_sigma_rad: float | None = None  # None: unknown, the frame's own


class VisualInertialInitializer:
    """Feed it the filter's IMU deltas and the camera's frames; :meth:`add_frame` returns the start once converged."""

    def __init__(self, camera: CameraCalibration, noise: ImuNoise, gravity: float, pixel_sigma: float,
                 options: VisualInertialOptions | None = None, association: AssociationOptions | None = None) -> None:
        self.options = opts = options or VisualInertialOptions()
        self.calibration = camera
        self.model = CameraModel(camera)
        self.R_BC = np.asarray(camera.R_BC, dtype=float)
        self.t_BC = np.asarray(camera.t_BC, dtype=float)
        self.gravity = float(gravity)
        self.pixel_sigma = float(pixel_sigma)
        self.accel_noise = float(np.max(noise.accel_noise_density))
        self.gyro_noise = float(np.max(noise.gyro_noise_density))
        frames_kept = max(opts.tracks.max_frames, int(math.ceil(opts.window_s * camera.rate_hz * 1.5)) + 2)
        self.tracker = FeatureTracker(self.model, dataclasses.replace(opts.tracks, max_frames=frames_kept), association)
        self._deltas: deque[ImuDelta] = deque()
        self.bias_prior = (np.zeros(3), 0.01, 0.1)  # b_g, σ_bg [rad/s], σ_ba [m/s²]
        self.time_offset_prior = (0.0, 0.0)  # the camera's residual offset and its sigma [s]; sigma 0: not solved
        self.attempts = 0
        self.progress: VisualStartProgress | None = None  # why it has not started yet (None before any frame)
        self.history: deque[VisualStartProgress] = deque(maxlen=50)  # each change of the failing check, in order
        self._measured: dict = {}
        self._passed_before = False
        self._last_solve_ns: int | None = None

    @property
    def last_failure(self) -> str:
        return "" if self.progress is None else self.progress.reason

    def reset(self) -> None:
        """Start over (after a filter reset, or once the start was taken)."""
        self.tracker.clear()
        self._deltas.clear()
        self._passed_before = False
        self.progress = None
        self._last_solve_ns = None

    def set_bias_prior(self, b_g: np.ndarray, sigma_g: float, sigma_a: float) -> None:
        self.bias_prior = (np.asarray(b_g, dtype=float).copy(), float(sigma_g), float(sigma_a))

    def set_time_offset_prior(self, value_s: float, sigma_s: float) -> None:
        """Solve the camera's residual time offset in the window, from this prior (a sigma of 0: take it as exact)."""
        self.time_offset_prior = (float(value_s), float(sigma_s))

    def add_delta(self, delta: ImuDelta) -> None:
        if self._deltas and delta.t0_ns != self._deltas[-1].t1_ns:
            self.reset()  # a hole in the IMU: the window's integrals would be wrong
        self._deltas.append(delta)
        horizon = int((self.options.window_s + 2.0) * 1e9)
        while len(self._deltas) > 2 and delta.t1_ns - self._deltas[0].t0_ns > horizon:
            self._deltas.popleft()

    def observe(self, features: FrameFeatures) -> None:
        """Only track the frame (no start wanted): whether the scene moves still tells a cruise from rest."""
        self.tracker.add(features)

    def image_moving(self, t_ns: int) -> bool:
        """The camera saw the scene move within the last ``still_window_s``: the vehicle is not at rest."""
        opts = self.options
        return self.tracker.image_moving(t_ns, opts.still_window_s, opts.still_flow_px)

    def add_frame(self, features: FrameFeatures, gauge: Gauge) -> VisualInertialStart | None:
        """Track the frame (IMU deltas must reach its time); the start, if the window has converged."""
        opts = self.options
        self.tracker.add(features)
        frames = self._usable_frames()
        span_s = (frames[-1].t_ns - frames[0].t_ns) * 1e-9 if frames else 0.0
        if len(frames) < 3 or span_s < opts.min_window_s:
            self._record(features.t_ns, "window", f"window too short ({len(frames)} frames over {span_s:.1f} s, "
                         f"{opts.min_window_s:g} s needed)", {"frames": len(frames), "window_s": span_s})
            return None
        if self._last_solve_ns is not None and (features.t_ns - self._last_solve_ns) * 1e-9 < opts.solve_every_s:
            return None
        self._last_solve_ns = features.t_ns
        self.attempts += 1
        self._measured = {"frames": len(frames), "window_s": span_s}
        try:
            start = self._solve(frames, gauge)
        except WindowFailure as why:
            self._record(features.t_ns, why.check, str(why), self._measured)
            self._passed_before = False
            return None
        passed, self._passed_before = self._passed_before, True
        if not passed:
            self._record(features.t_ns, "confirming", "the window passed; waiting for the next to agree", self._measured)
        return start if passed else None

    def _record(self, t_ns: int, check: str, reason: str, measured: dict) -> None:
        self.progress = VisualStartProgress(t_ns, check, reason, self.attempts, **measured)
        if not self.history or self.history[-1].check != check:
            self.history.append(self.progress)

    # ---------------------------------------------------------------------------- window
    def _usable_frames(self) -> list[TrackedFrame]:
        """Frames of the last ``window_s`` whose times are IMU delta boundaries covered by the buffer."""
        if not self._deltas:
            return []
        bounds = {d.t0_ns for d in self._deltas} | {self._deltas[-1].t1_ns}
        last = self.tracker.frames[-1].t_ns
        frames = [f for f in self.tracker.frames if f.t_ns in bounds and last - f.t_ns <= self.options.window_s * 1e9]
        if len(frames) > self.options.max_frames:
            pick = np.unique(np.round(np.linspace(0, len(frames) - 1, self.options.max_frames)).astype(int))
            frames = [frames[i] for i in pick]
        return frames

    def _problem(self, frames: list[TrackedFrame]) -> tuple[WindowProblem, np.ndarray, list[TrackedFrame]]:
        chosen, frames = self._choose_points(frames)
        t0 = frames[0].t_ns
        index = {int(t): i for i, t in enumerate(chosen)}
        obs_frame, obs_point, obs_xn = [], [], []
        for k, f in enumerate(frames):
            for r, t in enumerate(f.track_ids.tolist()):
                if t in index:
                    obs_frame.append(k)
                    obs_point.append(index[t])
                    obs_xn.append(f.xn[r])
        deltas = [d for d in self._deltas if t0 <= d.t0_ns and d.t1_ns <= frames[-1].t_ns]
        imu_t = np.array([(deltas[0].t0_ns - t0) * 1e-9] + [(d.t1_ns - t0) * 1e-9 for d in deltas])
        b_g, sigma_g, sigma_a = self.bias_prior
        problem = WindowProblem(
            frame_t=np.array([(f.t_ns - t0) * 1e-9 for f in frames]), obs_frame=np.array(obs_frame),
            obs_point=np.array(obs_point), obs_xn=np.array(obs_xn), imu_t=imu_t,
            dtheta=np.array([d.dtheta for d in deltas]), dvel=np.array([d.dvel for d in deltas]),
            R_BC=self.R_BC, t_BC=self.t_BC, focal_px=0.5 * (self.model.fx + self.model.fy),
            pixel_sigma=self.pixel_sigma, gravity=self.gravity, accel_noise=self.accel_noise,
            gyro_noise=self.gyro_noise, bias_g=b_g, sigma_bias_g=sigma_g, sigma_bias_a=sigma_a,
            time_offset_prior=self.time_offset_prior[0], sigma_time_offset=self.time_offset_prior[1],
        )
        return problem, chosen, frames

    def _choose_points(self, frames: list[TrackedFrame]) -> tuple[np.ndarray, list[TrackedFrame]]:
        """Tracks for the solve, and the frames they cover.

        Long tracks give parallax, but every frame needs its own rays, or its camera centre is
        free and the structure collapses onto it: tracks are taken longest first while some
        frame they are in has fewer than ``max_points / 4`` rays, then longest first; frames
        left with fewer than ``min_frame_rays`` are dropped from the window's start.
        """
        opts = self.options
        per_frame = [set(f.track_ids.tolist()) for f in frames]
        ids, counts = np.unique(np.concatenate([f.track_ids for f in frames]), return_counts=True)
        eligible = ids[counts >= opts.min_observations]
        length = dict(zip(ids.tolist(), counts.tolist()))
        order = sorted(eligible.tolist(), key=lambda t: -length[t])
        coverage = np.zeros(len(frames), dtype=int)
        target = max(opts.max_points // 4, opts.min_frame_rays)
        chosen: list[int] = []
        for t in order:
            if len(chosen) >= opts.max_points:
                break
            seen = np.array([t in ids_k for ids_k in per_frame])
            if np.any(coverage[seen] < target):
                chosen.append(t)
                coverage += seen
        taken = set(chosen)
        for t in order:
            if len(chosen) >= opts.max_points:
                break
            if t not in taken:
                chosen.append(t)
                coverage += np.array([t in ids_k for ids_k in per_frame])
        thin = np.flatnonzero(coverage < opts.min_frame_rays)
        first = int(thin[-1]) + 1 if len(thin) and thin[-1] < len(frames) - 1 else 0
        if len(thin) and thin[-1] == len(frames) - 1:
            raise WindowFailure("the last frame shares too few tracked points with the window", "tracks")
        frames = frames[first:]
        keep = set().union(*(per_frame[first:]))
        chosen = [t for t in chosen if t in keep and sum(t in ids_k for ids_k in per_frame[first:]) >= opts.min_observations]
        if len(chosen) < opts.min_points or len(frames) < 3:
            raise WindowFailure(f"{len(chosen)} points tracked over {opts.min_observations} frames (need {opts.min_points})",
                                "tracks")
        return np.array(chosen, dtype=np.int64), frames

    def _solve(self, frames: list[TrackedFrame], gauge: Gauge) -> VisualInertialStart:
        opts = self.options
        problem, chosen, frames = self._problem(frames)
        measured = self._measured
        measured.update(frames=problem.n_frames, window_s=float(problem.frame_t[-1]), tracks=problem.n_points,
                        excitation=acceleration_spread(problem))
        solution = solve_window(problem, opts.max_gravity_error)
        lay = Layout.of(problem)
        tilt = math.degrees(math.sqrt(max(np.linalg.eigvalsh(solution.cov[lay.G, lay.G]).max(), 0.0)))
        measured.update(scale_sigma_rel=scale_sigma(problem, solution), gravity_sigma_deg=tilt)
        if solution.residual_ratio > opts.max_residual_ratio:
            raise WindowFailure(f"residuals {solution.residual_ratio:.2f}x the noise", "residuals")
        if tilt > opts.max_tilt_sigma_deg:
            raise WindowFailure(f"gravity's direction not yet known (sigma over {opts.max_tilt_sigma_deg:g} deg)", "gravity")
        if measured["scale_sigma_rel"] > opts.max_scale_sigma_rel:
            raise WindowFailure(f"scale not yet known (sigma over {100 * opts.max_scale_sigma_rel:g} %)", "scale")
        last = frames[-1]
        seen = self._landmark_points(problem, solution, chosen, last)
        start = self._to_filter(problem, solution, seen, last, gauge, tilt, measured["scale_sigma_rel"])
        if not (np.all(np.isfinite(start.cov)) and np.all(np.diagonal(start.cov) > 0.0)):
            raise WindowFailure("the start's covariance is not positive", "information")
        measured["depth_sigma_rel"] = start.depth_sigma_rel
        v_limit = velocity_sigma_limit(opts, float(np.linalg.norm(start.v)))
        if start.sigma_velocity > v_limit:
            raise WindowFailure(f"velocity sigma {start.sigma_velocity:.3f} m/s", "velocity")
        if len(start.landmarks) < opts.min_landmarks:
            raise WindowFailure(f"{len(start.landmarks)} landmarks with a known depth in the last frame", "landmarks")
        if start.depth_sigma_rel > opts.max_depth_sigma_rel:
            raise WindowFailure(f"landmarks' depths not yet known (median sigma over {100 * opts.max_depth_sigma_rel:g} %)", "depth")
        return start

    def _landmark_points(self, problem: WindowProblem, solution: WindowSolution, chosen: np.ndarray,
                         last: TrackedFrame) -> list[tuple[int, int]]:
        """(point index, row in the last frame) of inlier points seen in the last frame, in front of it."""
        k_last = problem.n_frames - 1
        inlier_last = solution.inliers & (problem.obs_frame == k_last)
        seen_points = set(problem.obs_point[inlier_last].tolist())
        rows = {int(t): r for r, t in enumerate(last.track_ids)}
        out = []
        for j in sorted(seen_points):
            d = solution.R[k_last].T @ (solution.points[j] - solution.p[k_last]) - self.t_BC
            if (self.R_BC.T @ d)[2] > 0.0:
                out.append((j, rows[int(chosen[j])]))
        return out

    # -------------------------------------------------------------------- to the filter
    def _to_filter(self, problem: WindowProblem, solution: WindowSolution, seen: list[tuple[int, int]],
                   last: TrackedFrame, gauge: Gauge, tilt_deg: float, scale_sigma_rel: float) -> VisualInertialStart:
        """Nominal state at the last frame and its covariance, by first-order change of variables."""
        opts = self.options
        lay = Layout.of(problem)
        k = problem.n_frames - 1
        points = [j for j, _ in seen]
        heading_sigma = math.radians(opts.heading_sigma_deg) if gauge.heading_sigma_rad is None else gauge.heading_sigma_rad

        rotations: dict[bytes, np.ndarray] = {}

        def state(g_dir, b_g, b_a, p_k, v_k, f, shift, turn):
            R_k = rotations.get(b_g.tobytes())
            if R_k is None:
                R_k = rotations[b_g.tobytes()] = integrate(problem.imu_t, problem.dtheta, problem.dvel, b_g,
                                                           problem.frame_t[-1:]).R[0]
            R_W0 = _levelling(g_dir)
            yaw = float(euler_from_quat(rot_to_quat(R_W0 @ R_k))[2])
            R_W0 = so3_exp(np.array([0.0, 0.0, gauge.heading_rad + turn - yaw])) @ R_W0
            R_WB = R_W0 @ R_k
            p = gauge.p + shift
            anchor = p + R_WB @ self.t_BC
            rays = (f[points] - p_k) @ R_W0.T + p - anchor
            theta, phi = angles(rays)
            y = np.column_stack([np.tile(anchor, (len(points), 1)), theta, phi, 1.0 / np.linalg.norm(rays, axis=1)])
            return p, R_W0 @ v_k, R_WB, b_g, b_a, y

        base = (solution.gravity_dir, solution.bias_g, solution.bias_a, solution.p[k], solution.v[k], solution.points)
        nominal = state(*base, np.zeros(3), 0.0)
        L = len(points)
        n_err = ROBOT_DIM + LANDMARK_DIM * L

        def error(other) -> np.ndarray:
            p, v, R, b_g, b_a, y = other
            e = np.empty(n_err)
            e[0:3], e[3:6], e[6:9] = p - nominal[0], v - nominal[1], so3_log(R @ nominal[2].T)
            e[9:12], e[12:15] = b_g - nominal[3], b_a - nominal[4]
            e[15:] = (y - nominal[5]).reshape(-1)
            return e

        # Columns: the solution's unknowns that move the state at the last frame, then the gauge.
        cols = list(range(lay.G.start, lay.BA.stop)) + list(range(lay.p(k).start, lay.p(k).stop)) \
            + list(range(lay.v(k).start, lay.v(k).stop)) \
            + [lay.point(j).start + a for j in points for a in range(3)]
        eps = 1e-6
        E = np.zeros((n_err, len(cols)))
        tangent = solution.tangent
        for c, col in enumerate(cols):
            g_dir, b_g, b_a, p_k, v_k, f = (np.array(x, copy=True) for x in base)
            if col < lay.BG.start:
                g_dir = so3_exp(tangent[:, col] * eps) @ g_dir
            elif col < lay.BA.start:
                b_g[col - lay.BG.start] += eps
            elif col < lay.BA.stop:
                b_a[col - lay.BA.start] += eps
            elif lay.p(k).start <= col < lay.p(k).stop:
                p_k[col - lay.p(k).start] += eps
            elif lay.v(k).start <= col < lay.v(k).stop:
                v_k[col - lay.v(k).start] += eps
            else:
                j, a = divmod(col - lay.point(0).start, 3)
                f[j, a] += eps
            E[:, c] = error(state(g_dir, b_g, b_a, p_k, v_k, f, np.zeros(3), 0.0)) / eps
        cov = E @ solution.cov[np.ix_(cols, cols)] @ E.T
        # The gauge: the frame's origin and heading, known to what the caller says.
        G = np.zeros((n_err, 4))
        for a in range(3):
            shift = np.zeros(3)
            shift[a] = eps
            G[:, a] = error(state(*base, shift, 0.0)) / eps
        G[:, 3] = error(state(*base, np.zeros(3), eps)) / eps
        cov += G @ np.diag([opts.position_sigma_m**2] * 3 + [heading_sigma**2]) @ G.T
        cov = 0.5 * (cov + cov.T)
        rho = nominal[5][:, 5]
        sigma_rho = np.sqrt(np.maximum(covariance.block_variances(cov, slice(ROBOT_DIM + INVERSE_DEPTH, None, LANDMARK_DIM)), 0.0))
        order = np.argsort(sigma_rho / rho)[: opts.max_landmarks]
        keep = np.concatenate([np.arange(ROBOT_DIM), ROBOT_DIM + (LANDMARK_DIM * order[:, None] + np.arange(LANDMARK_DIM)).ravel()])
        rows = np.array([r for _, r in seen], dtype=int)[order]
        start_cov = cov[np.ix_(keep, keep)]
        if lay.time_offset:
            # The state at the last stamp does not depend on t_d, but its errors do, through the window: the
            # offset's row is the window's, mapped like the others (the gauge is independent of it).
            cross = (E @ solution.cov[cols, lay.TD.start])[keep]
            start_cov = covariance.append_states(start_cov, cross[None, :], solution.cov[lay.TD, lay.TD])
            start_cov = start_cov[np.ix_(_offset_after_robot(len(start_cov)), _offset_after_robot(len(start_cov)))]
        return VisualInertialStart(
            t_ns=last.t_ns, p=nominal[0], v=nominal[1], q=rot_to_quat(nominal[2]), b_g=nominal[3], b_a=nominal[4],
            landmarks=nominal[5][order], cov=start_cov, descriptors=last.descriptors[rows],
            binary=last.binary, window_s=float(problem.frame_t[-1]), n_frames=problem.n_frames,
            n_points=problem.n_points, residual_ratio=solution.residual_ratio, sigma_tilt_deg=tilt_deg,
            sigma_scale_rel=scale_sigma_rel,
            sigma_velocity=float(np.sqrt(np.max(covariance.block_variances(cov, V)))),
            depth_sigma_rel=float(np.median(sigma_rho[order] / rho[order])) if len(order) else math.inf,
            time_offset_s=solution.time_offset if lay.time_offset else None,
        )


def velocity_sigma_limit(options: VisualInertialOptions, speed: float) -> float:
    """The velocity sigma a start may have at ``speed``: a floor plus the scale's own limit of the speed. The
    window finds the velocity only up to the scale, so a tighter relative limit than the scale's would refuse
    starts the scale test accepts (a cruise at 8 m/s with the scale known to 9 %)."""
    return options.max_velocity_sigma + options.max_scale_sigma_rel * speed


def _offset_after_robot(n: int) -> np.ndarray:
    """The order that moves the last of ``n`` states (the time offset) between the robot and the landmarks."""
    return np.r_[0:ROBOT_DIM, n - 1, ROBOT_DIM : n - 1]


def _levelling(g_dir: np.ndarray) -> np.ndarray:
    """A rotation taking the unit gravity direction ``g_dir`` (B0) onto world down."""
    down = np.array([0.0, 0.0, 1.0])
    axis = np.cross(g_dir, down)
    s, c = np.linalg.norm(axis), float(g_dir @ down)
    if s < 1e-12:
        return np.eye(3) if c > 0.0 else np.diag([1.0, -1.0, -1.0])
    return so3_exp(axis / s * math.atan2(s, c))


__all__ = ["Gauge", "VisualInertialInitializer", "VisualInertialOptions", "VisualInertialStart", "VisualStartProgress",
           "tangent_basis"]
