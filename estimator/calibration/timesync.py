"""IMU–camera time offset by correlation (thesis 5.1.2).

The camera sees its own rotation: features tracked between consecutive frames give the relative
rotation of each frame pair (a homography for a pure rotation or a planar scene, the essential
matrix for a scene with depth). The gyro gives the same rotation once integrated over the same interval — of
the IMU clock. Shifting the frame stamps by a candidate offset and correlating the two sequences
of rotation vectors (in camera axes, through ``R_BC``), the true offset is where they agree best.
The peak's curvature, read as a least-squares fit, gives the offset's 1σ: its sharpness.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from vtolpose.estimator.core.calibration import CameraCalibration
from vtolpose.estimator.core.rotation import so3_log

RECORD_ADVICE = (
    "record the camera looking at a static, textured, well-lit scene while it is turned about all three axes at "
    "30-90 deg/s with changes of direction (a few swings a second is ideal) for 20-60 s")


class TimeSyncError(ValueError):
    """The record cannot give the offset; the message says what to record instead."""


@dataclass(frozen=True, slots=True)
class TrackOptions:
    max_corners: int = 300
    min_tracks: int = 20
    forward_backward_px: float = 0.5
    planar_px: float = 0.5  # median residual of a homography below which the scene counts as one plane
    max_track_width: int = 400  # larger frames are halved (pyrDown) for tracking: blur and big motions track better


@dataclass(frozen=True, slots=True)
class FrameRotations:
    """Rotation of the camera between consecutive frames: ``rotvec[k]`` takes frame ``t1`` axes to
    ``t0`` axes (the integral of the camera's angular rate over the pair, camera axes)."""

    t0_ns: np.ndarray
    t1_ns: np.ndarray
    rotvec: np.ndarray
    tracks: np.ndarray
    pairs_skipped: int
    frames: int


@dataclass(frozen=True, slots=True)
class TimeSyncOptions:
    max_offset_s: float = 0.2
    step_s: float = 0.001
    min_pairs: int = 20
    min_rate: float = 0.1  # rad/s: RMS of the camera's rotation rate (≈ 6 °/s)
    max_sigma_s: float = 0.005
    min_correlation: float = 0.5


@dataclass(frozen=True, slots=True)
class TimeSyncResult:
    """The offset to add to camera stamps to put them on the IMU clock, and how sharp it is."""

    lags_s: np.ndarray
    correlation: np.ndarray
    offset_s: float
    sigma_s: float
    peak: float
    n_pairs: int
    rate_rms: float  # rad/s, camera rotation rate
    residual_rms: float  # rad, camera − gyro rotation per pair at the offset
    t_mid_s: np.ndarray  # per pair, from the first frame (for plots)
    camera_rate: np.ndarray  # (M, 3) rad/s
    gyro_rate: np.ndarray  # (M, 3) rad/s in camera axes, at the offset


def _plane_rotation(x0, x1, camera: CameraCalibration, options: TrackOptions, normal: np.ndarray | None):
    """Rotation (frame-1 axes → frame-0 axes) and plane normal from a homography, or None when the
    tracks do not lie on one plane. Of the decompositions, the one whose normal is nearest the
    previous pair's (or, first, the one facing the camera most) is taken: a ground or a table
    turns slowly in the camera's view."""
    import cv2  # on first use: a process that never needs OpenCV never loads it (~16 MB)

    H, mask = cv2.findHomography(x0, x1, cv2.RANSAC, 1.0 / camera.fx)
    if H is None or mask is None or int(mask.sum()) < options.min_tracks:
        return None
    inl = mask.ravel() == 1
    mapped = cv2.perspectiveTransform(x0[inl].reshape(-1, 1, 2), H).reshape(-1, 2)
    if np.median(np.linalg.norm(mapped - x1[inl], axis=1)) * camera.fx > options.planar_px:
        return None
    _, rotations, translations, normals = cv2.decomposeHomographyMat(H, np.eye(3))
    reference = np.array([0.0, 0.0, 1.0]) if normal is None else normal
    best = max(range(len(rotations)), key=lambda i: abs(float(normals[i].ravel() @ reference)))
    n = normals[best].ravel()
    # Without translation the normal is arbitrary: keep the last one that a baseline showed.
    if np.linalg.norm(translations[best]) < 0.01:
        return rotations[best].T, normal
    return rotations[best].T, n * np.sign(n @ reference)


def _pair_rotation(p0, p1, camera: CameraCalibration, options: TrackOptions, normal: np.ndarray | None):
    """Rotation taking frame-1 camera axes to frame-0 axes from tracked pixels p0 → p1, and the
    scene plane's normal. A homography covers both a pure rotation (any scene) and a planar scene
    (ground, table); a scene with depth and parallax falls back to the essential matrix."""
    import cv2

    K, dist = camera.K, camera.distortion
    undistort = cv2.fisheye.undistortPoints if camera.model == "equidistant" else cv2.undistortPoints
    x0 = undistort(p0.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    x1 = undistort(p1.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    plane = _plane_rotation(x0, x1, camera, options, normal)
    if plane is not None:
        return plane
    try:
        E, mask = cv2.findEssentialMat(x0, x1, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=1.0 / camera.fx)
    except cv2.error:  # a degenerate pair (OpenCV ≥ 5.1's solver refuses it): no rotation from it
        return None, normal
    if E is None or E.shape != (3, 3) or mask is None or int(mask.sum()) < options.min_tracks:
        return None, normal
    _, R_10, _, _ = cv2.recoverPose(E, x0, x1, np.eye(3), mask=mask)  # x1 = R_10 x0 + t
    return R_10.T, normal


def frame_rotations(
    frames: Iterable[tuple[int, np.ndarray]], camera: CameraCalibration, options: TrackOptions = TrackOptions()
) -> FrameRotations:
    """Relative rotations of consecutive frames ``(t_ns, grey uint8 image)`` (KLT tracks with a
    forward–backward check). Pairs with too few tracks are skipped and counted."""
    import cv2

    t0s, t1s, rotvecs, tracks = [], [], [], []
    skipped = frames_seen = 0
    previous = normal = None
    for t_ns, full in frames:
        frames_seen += 1
        image, scale = full, 1.0
        while image.shape[1] > options.max_track_width:
            image, scale = cv2.pyrDown(image), 2.0 * scale  # pixel i of the half image sits at 2i of the full
        if previous is not None:
            t_prev, prev = previous
            corners = cv2.goodFeaturesToTrack(prev, options.max_corners, 0.01, 8)
            R = None
            n_good = 0
            if corners is not None and len(corners) >= options.min_tracks:
                fwd, st1, _ = cv2.calcOpticalFlowPyrLK(prev, image, corners, None, winSize=(21, 21), maxLevel=3)
                back, st2, _ = cv2.calcOpticalFlowPyrLK(image, prev, fwd, None, winSize=(21, 21), maxLevel=3)
                good = ((st1.ravel() == 1) & (st2.ravel() == 1)
                        & (np.linalg.norm((back - corners).reshape(-1, 2), axis=1) < options.forward_backward_px))
                n_good = int(good.sum())
                if n_good >= options.min_tracks:
                    R, normal = _pair_rotation(scale * corners.reshape(-1, 2)[good].astype(float),
                                               scale * fwd.reshape(-1, 2)[good].astype(float), camera, options, normal)
            if R is None:
                skipped += 1
            else:
                t0s.append(t_prev)
                t1s.append(t_ns)
                rotvecs.append(so3_log(R))
                tracks.append(n_good)
        previous = (t_ns, image)
    as_ns = lambda v: np.array(v, dtype=np.int64)  # noqa: E731
    return FrameRotations(as_ns(t0s), as_ns(t1s), np.array(rotvecs).reshape(-1, 3), np.array(tracks), skipped, frames_seen)


def _gyro_angle(imu_t_ns: np.ndarray, gyro: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Running integral of the body rate (trapezoid) at the IMU sample times [s from the first]."""
    t = (imu_t_ns - imu_t_ns[0]) * 1e-9
    steps = 0.5 * (gyro[1:] + gyro[:-1]) * np.diff(t)[:, None]
    return t, np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])


class _Scan:
    """Camera rotation vectors against the integrated gyro, over a grid of candidate offsets."""

    def __init__(self, t0, t1, camera_rotvec, t_imu, angle, R_BC, lags) -> None:
        self.t0, self.t1, self.t_imu, self.angle, self.lags = t0, t1, t_imu, angle, lags
        self.to_camera = np.asarray(R_BC, float).T
        self.a = camera_rotvec - camera_rotvec.mean(axis=0)  # centred: the gyro bias drops out

    def gyro_rotvec(self, lag: float, keep=slice(None)) -> np.ndarray:
        """The gyro's rotation over each pair's interval shifted by ``lag``, camera axes, centred."""
        ends = [np.column_stack([np.interp(t[keep] + lag, self.t_imu, self.angle[:, i]) for i in range(3)])
                for t in (self.t0, self.t1)]
        b = (ends[1] - ends[0]) @ self.to_camera.T
        return b - b.mean(axis=0)

    def run(self, keep=slice(None)) -> tuple[np.ndarray, np.ndarray, float, float, np.ndarray]:
        """Correlation and squared difference per lag; the refined peak; its cost curvature; residuals."""
        a = self.a[keep] - self.a[keep].mean(axis=0)
        rho, cost = np.empty(len(self.lags)), np.empty(len(self.lags))
        for i, lag in enumerate(self.lags):
            b = self.gyro_rotvec(lag, keep)
            rho[i] = float(np.sum(a * b) / math.sqrt(np.sum(a * a) * np.sum(b * b)))
            cost[i] = float(np.sum((a - b) ** 2))
        k = int(np.argmax(rho))
        if k in (0, len(self.lags) - 1):
            return rho, cost, float(self.lags[k]), 0.0, a
        lags = self.lags
        lo, hi = max(0, k - 3), min(len(lags), k + 4)
        c2, c1, _ = np.polyfit(lags[lo:hi] - lags[k], rho[lo:hi], 2)
        shift = np.clip(-c1 / (2.0 * c2), lags[lo] - lags[k], lags[hi - 1] - lags[k]) if c2 < 0 else 0.0
        offset = float(lags[k] + shift)
        q2 = float(np.polyfit(lags[lo:hi] - offset, cost[lo:hi], 2)[0])
        return rho, cost, offset, q2, a - self.gyro_rotvec(offset, keep)


def _rate_rms(rate: np.ndarray) -> float:
    """RMS of the camera's rotation rate about its mean, over the pairs whose rate is within five times the
    median: one pair whose rotation was decomposed wrongly (3 rad in 60 ms on a hand-held walk) would
    otherwise report a swing of 200 deg/s for a camera turning at 10."""
    speed = np.linalg.norm(rate, axis=1)
    sane = rate[speed <= 5.0 * np.median(speed)] if np.median(speed) > 0.0 else rate
    return float(np.sqrt(np.mean(np.sum((sane - sane.mean(axis=0)) ** 2, axis=1))))


def correlate(
    rotations: FrameRotations, imu_t_ns: np.ndarray, gyro_b: np.ndarray, R_BC: np.ndarray,
    options: TimeSyncOptions = TimeSyncOptions(),
) -> TimeSyncResult:
    """Scan the offset; raise :class:`TimeSyncError` when the record cannot show it sharply.

    Pairs whose rotation disagrees with the gyro by more than five times the median at the first
    peak (a frame pair that saw two planes, a moving object) are left out of a second pass.
    """
    o = options
    imu_t_ns = np.asarray(imu_t_ns, dtype=np.int64)
    t_imu, angle = _gyro_angle(imu_t_ns, np.asarray(gyro_b, float))
    t0 = (rotations.t0_ns - imu_t_ns[0]) * 1e-9
    t1 = (rotations.t1_ns - imu_t_ns[0]) * 1e-9
    inside = (t0 - o.max_offset_s >= t_imu[0]) & (t1 + o.max_offset_s <= t_imu[-1])
    t0, t1, cam = t0[inside], t1[inside], rotations.rotvec[inside]
    if len(t0) < o.min_pairs:
        raise TimeSyncError(
            f"only {len(t0)} frame pairs were tracked within the IMU record ({rotations.frames} frames, "
            f"{rotations.pairs_skipped} pairs without enough tracks); {o.min_pairs} are needed: {RECORD_ADVICE}")
    rate = cam / (t1 - t0)[:, None]
    rate_rms = _rate_rms(rate)
    if rate_rms < o.min_rate:
        raise TimeSyncError(
            f"too little rotation to correlate: the camera turned at {math.degrees(rate_rms):.1f} deg/s RMS "
            f"(at least {math.degrees(o.min_rate):.0f} needed): {RECORD_ADVICE}")
    n_side = int(round(o.max_offset_s / o.step_s))
    scan = _Scan(t0, t1, cam, t_imu, angle, R_BC, o.step_s * np.arange(-n_side, n_side + 1))
    rho, cost, offset, q2, residual = scan.run()
    norms = np.linalg.norm(residual, axis=1)
    keep = norms <= 5.0 * np.median(norms)
    if q2 > 0.0 and not np.all(keep) and np.count_nonzero(keep) >= o.min_pairs:
        rho, cost, offset, q2, residual = scan.run(keep)
    M = len(residual)
    peak = float(np.max(rho))
    if q2 == 0.0:
        raise TimeSyncError(
            f"the correlation is highest at the edge of the scan ({offset * 1e3:+.0f} ms): widen the scan beyond "
            f"+-{o.max_offset_s * 1e3:.0f} ms, or {RECORD_ADVICE}")
    s2 = float(np.sum(residual**2)) / max(3 * M - 4, 1)
    sigma = math.sqrt(s2 / q2) if q2 > 0 else math.inf  # cost ≈ C* + q2 δ², so σ² = 2 s² / C'' = s² / q2
    if peak < o.min_correlation or sigma > o.max_sigma_s:
        raise TimeSyncError(
            f"the offset is not sharp: correlation peak {peak:.2f} at {offset * 1e3:+.1f} ms, +-{sigma * 1e3:.1f} ms "
            f"(limits: peak {o.min_correlation:g}, +-{o.max_sigma_s * 1e3:g} ms); check the camera intrinsics and R_BC, "
            f"then {RECORD_ADVICE}")
    kept = np.flatnonzero(keep) if M < len(t0) else np.arange(len(t0))
    dt = (t1 - t0)[kept]
    return TimeSyncResult(
        lags_s=scan.lags, correlation=rho, offset_s=offset, sigma_s=sigma, peak=peak, n_pairs=M, rate_rms=rate_rms,
        residual_rms=math.sqrt(s2), t_mid_s=0.5 * (t0 + t1)[kept] - t0[0], camera_rate=rate[kept],
        gyro_rate=rate[kept] - residual / dt[:, None],  # the camera's rate less the disagreement
    )
