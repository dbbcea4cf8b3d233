"""Camera calibration from chessboard views (thesis 5.3): OpenCV's pinhole + 5-coefficient model.

OpenCV finds the inner corners and solves for intrinsics, distortion (k1 k2 p1 p2 k3) and one
board pose per view (Zhang's method refined by Levenberg–Marquardt). What this module adds is
the judgement a field team needs: the RMS reprojection error overall and per view, which views
to drop, and a refusal when the views cannot pin the model down (too few, or too alike).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vtolpose.estimator.core.calibration import CameraCalibration

RECORD_ADVICE = (
    "record 10-20 views with the whole board visible and sharp, tilted by 30-45 degrees in different "
    "directions, at several distances, with the board reaching every corner of the image across the views")


class ChessboardError(ValueError):
    """The views cannot give a trustworthy calibration; the message says what to record instead."""


@dataclass(frozen=True, slots=True)
class Board:
    """A chessboard by its inner corners (``cols`` × ``rows``) and square size [m]."""

    cols: int
    rows: int
    square_m: float

    def __post_init__(self) -> None:
        if self.cols < 3 or self.rows < 3 or not self.square_m > 0.0:
            raise ValueError(f"board: need at least 3x3 inner corners and a positive square size, got {self}")

    @property
    def pattern(self) -> tuple[int, int]:
        return (self.cols, self.rows)

    def object_points(self) -> np.ndarray:
        """Corner positions on the board plane (z = 0), row by row as OpenCV reports them."""
        j, i = np.mgrid[0 : self.rows, 0 : self.cols]
        return np.column_stack([i.ravel(), j.ravel(), np.zeros(i.size)]).astype(np.float32) * np.float32(self.square_m)


def find_corners(image: np.ndarray, board: Board) -> np.ndarray | None:
    """Inner corners (N, 2) refined to sub-pixel accuracy, or None if the board is not found whole."""
    import cv2  # on first use: a process that never needs OpenCV never loads it (~16 MB)

    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(grey, board.pattern, flags=flags)
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    corners = cv2.cornerSubPix(grey, corners, (5, 5), (-1, -1), criteria)
    return corners.reshape(-1, 2).astype(np.float64)


@dataclass(frozen=True, slots=True)
class ChessboardCalibration:
    width: int
    height: int
    K: np.ndarray
    distortion: np.ndarray  # k1 k2 p1 p2 k3
    rms_px: float
    view_names: list[str]
    view_rms_px: np.ndarray
    residuals: list[np.ndarray]  # per view (N, 2): measured − reprojected [px]
    intrinsic_sigma: np.ndarray  # 1σ of fx fy cx cy k1 k2 p1 p2 k3
    drop: list[str] = field(default_factory=list)  # views whose error stands out

    def camera(self) -> CameraCalibration:
        K = self.K
        return CameraCalibration(self.width, self.height, K[0, 0], K[1, 1], K[0, 2], K[1, 2], self.distortion.copy())


def outlier_views(names: list[str], rms: np.ndarray) -> list[str]:
    """Views whose RMS error is over twice the median and 0.25 px above it: a blurred image, a
    mis-ordered corner, a board that bent — worth dropping and calibrating again."""
    median = float(np.median(rms))
    limit = max(2.0 * median, median + 0.25)
    return [n for n, r in zip(names, rms) if r > limit]


def calibrate_views(
    views: list[tuple[str, np.ndarray]],
    board: Board,
    image_size: tuple[int, int],
    min_views: int = 8,
    max_relative_sigma: float = 0.02,
    min_tilt_deg: float = 10.0,
) -> ChessboardCalibration:
    """Calibrate from the corners of each view (``name``, (N, 2)); ``image_size`` is (width, height).

    Refuses fewer than ``min_views`` views, fewer than three boards tilted by ``min_tilt_deg``
    against the image plane, and views so alike that the focal length or principal point is
    uncertain by more than ``max_relative_sigma`` of its value.
    """
    import cv2

    if len(views) < min_views:
        raise ChessboardError(
            f"the chessboard ({board.cols}x{board.rows} inner corners) was found in {len(views)} view(s); at least "
            f"{min_views} are needed: {RECORD_ADVICE}")
    obj = board.object_points()
    n = len(obj)
    for name, c in views:
        if np.shape(c) != (n, 2):
            raise ValueError(f"view {name}: expected {n} corners (N, 2), got shape {np.shape(c)}")
    image_points = [np.asarray(c, np.float32).reshape(-1, 1, 2) for _, c in views]
    object_points = [obj.reshape(-1, 1, 3)] * len(views)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-12)
    rms, K, dist, rvecs, tvecs, sigma_intr, _, per_view = cv2.calibrateCameraExtended(
        object_points, image_points, tuple(int(v) for v in image_size), None, None, criteria=criteria)
    sigma = sigma_intr.reshape(-1)[:9]
    relative = sigma[:4] / np.abs(np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]))
    # Boards parallel to the image plane leave the focal length free (Zhang's method needs tilted
    # planes), and OpenCV's uncertainties do not show it; count the tilted views instead.
    tilts = np.degrees([np.arccos(min(1.0, abs(cv2.Rodrigues(r)[0][2, 2]))) for r in rvecs])
    tilted = int(np.count_nonzero(tilts >= min_tilt_deg))
    if tilted < 3 or not np.all(np.isfinite(relative)) or np.max(relative) > max_relative_sigma:
        raise ChessboardError(
            f"the {len(views)} views do not determine the camera ({tilted} tilted by {min_tilt_deg:g} degrees or more, "
            f"3 needed; focal length / principal point uncertain by up to {100 * np.nanmax(relative):.1f} %): the views "
            f"are too alike; {RECORD_ADVICE}")
    residuals = []
    for (name, c), rvec, tvec in zip(views, rvecs, tvecs):
        projected, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
        residuals.append(np.asarray(c, float) - projected.reshape(-1, 2))
    view_rms = np.array([np.sqrt(np.mean(np.sum(r * r, axis=1))) for r in residuals])
    names = [name for name, _ in views]
    return ChessboardCalibration(
        width=int(image_size[0]),
        height=int(image_size[1]),
        K=K,
        distortion=np.asarray(dist, float).reshape(-1)[:5],
        rms_px=float(rms),
        view_names=names,
        view_rms_px=view_rms,
        residuals=residuals,
        intrinsic_sigma=sigma,
        drop=outlier_views(names, view_rms),
    )
