"""Features carried from frame to frame by optical flow, with a full detection every few frames.

A detector (SIFT by default) costs tens of milliseconds a frame; pyramidal Lucas–Kanade moves
the previous frame's points onto the next in a few. Between two detections each tracked point
keeps the descriptor and response of the detection it descends from, so the EKF-SLAM's
association (descriptor distance inside the predicted gate) works unchanged: a landmark made
from a tracked point meets the very descriptor it was made with. A point is kept only when
tracking it back lands within ``max_flow_error_px`` of where it started (the forward–backward
check drops points that slid along an edge, the window's residual those covered by something else), and a new detection comes every
``track_between + 1`` frames or as soon as fewer than ``min_tracked_fraction`` of the last
detection's points survive. A frame out of order, a rejected frame, or a change of image size
starts again from a detection.

A camera swung at a few frames a second moves its points tens of pixels and turns them between two
frames, past what the pyramid's coarsest level finds alone; but the motion of one frame pair is much
like the next's. So the image motion of the last pair tracked (a similarity fitted to its kept points,
RANSAC) is each point's first guess in the next pair, forward, and its inverse the guess of the check
back: the flow only corrects the guess, and the check stays the same test.

Computation only: the tracker holds the last image and its features, nothing else, and its
output depends only on the frames given in order.
"""

from __future__ import annotations

import time

import numpy as np

from vtolpose.estimator.vision.features import FeatureOptions, FrameFeatures, extract_features, image_digest, working_frame
from vtolpose.estimator.vision.frame_quality import frame_problem

LK_WINDOW_PX = 21  # Lucas–Kanade window, each pyramid level
LK_LEVELS = 3  # pyramid levels above the frame: flows of up to ~2^3 × the window's reach
BORDER_PX = 2.0  # tracked points this close to the edge are dropped (their window leaves the image)
MIN_MOTION_POINTS = 12  # kept points a pair needs for its image motion to be the next pair's guess
MOTION_INLIER_PX = 2.0  # RANSAC: a point this far from the fitted similarity is not its evidence
MAX_PATCH_RESIDUAL_DN = 8.0  # mean absolute grey-level difference of a point's window once aligned: a few DN is
# sensor noise; a point covered by another scene can pass the forward-backward check, not this (17-28 DN)


class FeatureTracker:
    """Call :meth:`features` with the frames in time order; it detects or tracks as ``options`` say."""

    def __init__(self, options: FeatureOptions) -> None:
        if options.track_between < 1:
            raise ValueError("a feature tracker needs features.track_between >= 1 (0 detects every frame)")
        self.options = options
        self._image: np.ndarray | None = None
        self._last: FrameFeatures | None = None
        self._motion: np.ndarray | None = None  # the last tracked pair's image motion (2 × 3 similarity)
        self._detected = 0  # points of the last detection
        self._since_detection = 0  # frames tracked since it
        self.detections = 0
        self.tracked_frames = 0

    def reset(self) -> None:
        """Forget the last frame: the next one is detected, and tracked without a guess."""
        self._image, self._last, self._motion = None, None, None

    def features(self, image: np.ndarray, t_ns: int, expected_shape: tuple[int, int] | None = None) -> FrameFeatures:
        """Features of the frame at ``t_ns``: tracked from the last frame, or detected afresh."""
        image, expected_shape = working_frame(np.asarray(image), expected_shape, self.options.working_width)
        last = self._last
        if last is None or t_ns <= last.t_ns or self._image is None or self._image.shape != image.shape \
                or self._since_detection >= self.options.track_between:
            return self._detect(image, t_ns, expected_shape)
        started, started_cpu = time.perf_counter(), time.thread_time()
        digest = image_digest(image) if image.size else b""
        problem = frame_problem(image, expected_shape, self.options.quality)
        if problem is not None:
            self.reset()
            return FrameFeatures.rejected(t_ns, image.shape, problem, digest)
        keep, points = self._track(self._image, image, last.keypoints)
        self._motion = _image_motion(last.keypoints[keep], points[keep])
        if np.count_nonzero(keep) < self.options.min_tracked_fraction * self._detected:
            return self._detect(image, t_ns, expected_shape)
        self._image = image
        self._since_detection += 1
        self.tracked_frames += 1
        self._last = FrameFeatures(
            t_ns, points[keep], last.descriptors[keep], last.responses[keep], image.shape[:2], binary=last.binary,
            digest=digest, extract_ms=(time.perf_counter() - started) * 1e3,
            extract_cpu_ms=(time.thread_time() - started_cpu) * 1e3)
        return self._last

    def _detect(self, image: np.ndarray, t_ns: int, expected_shape: tuple[int, int] | None) -> FrameFeatures:
        found = extract_features(image, t_ns, self.options, expected_shape)
        if self._last is not None and t_ns <= self._last.t_ns:
            return found  # out of order: answered, but the tracker keeps its newer frame
        if found.problem is not None or len(found) == 0:
            self.reset()
            return found
        self._image, self._last = image, found
        self._detected, self._since_detection = len(found), 0
        self.detections += 1
        return found

    def _track(self, before: np.ndarray, after: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where ``points`` of ``before`` went in ``after``, and which of them passed the forward–backward check."""
        import cv2  # on first use, as in features.py

        if len(points) == 0:
            return np.zeros(0, dtype=bool), points
        start = points.astype(np.float32).reshape(-1, 1, 2)
        lk = {"winSize": (LK_WINDOW_PX, LK_WINDOW_PX), "maxLevel": LK_LEVELS,
              "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)}
        motion = self._motion
        if motion is None:
            ahead, ok_ahead, residual = cv2.calcOpticalFlowPyrLK(before, after, start, None, **lk)
            back, ok_back, _ = cv2.calcOpticalFlowPyrLK(after, before, ahead, None, **lk)
        else:
            guess = _moved(start, motion)
            ahead, ok_ahead, residual = cv2.calcOpticalFlowPyrLK(before, after, start, guess, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                                                 **lk)
            back, ok_back, _ = cv2.calcOpticalFlowPyrLK(after, before, ahead, _moved(ahead, cv2.invertAffineTransform(motion)),
                                                        flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        ahead, back = ahead.reshape(-1, 2).astype(float), back.reshape(-1, 2).astype(float)
        height, width = after.shape[:2]
        inside = ((ahead[:, 0] >= BORDER_PX) & (ahead[:, 0] <= width - 1 - BORDER_PX)
                  & (ahead[:, 1] >= BORDER_PX) & (ahead[:, 1] <= height - 1 - BORDER_PX))
        round_trip = np.linalg.norm(back - points, axis=1)
        keep = ok_ahead.ravel().astype(bool) & ok_back.ravel().astype(bool) & inside \
            & (round_trip < self.options.max_flow_error_px) & (residual.ravel() < MAX_PATCH_RESIDUAL_DN)
        return keep, ahead


def _moved(points: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """``points`` (n × 1 × 2, float32) under a 2 × 3 image motion: a first guess for the flow."""
    flat = points.reshape(-1, 2).astype(float)
    return (flat @ motion[:, :2].T + motion[:, 2]).astype(np.float32).reshape(-1, 1, 2)


def _image_motion(before: np.ndarray, after: np.ndarray) -> np.ndarray | None:
    """The similarity (rotation, scale, shift) that carries the kept points of one frame onto the next, fitted
    robustly; None when too few points, or too few agree, to say."""
    import cv2

    if len(before) < MIN_MOTION_POINTS:
        return None
    motion, inliers = cv2.estimateAffinePartial2D(before.astype(np.float32), after.astype(np.float32), method=cv2.RANSAC,
                                                  ransacReprojThreshold=MOTION_INLIER_PX)
    if motion is None or inliers is None or int(inliers.sum()) < MIN_MOTION_POINTS:
        return None
    return motion


class FrameExtractor:
    """A frame's features as ``options`` say: detected in every frame, or tracked between detections.

    The one extraction of the camera's workers, threads or a process alike, so that both give the same
    features. Tracking makes a frame's features depend on the frame before: the frames must then come one
    at a time, in time order (:attr:`in_order`), and the image is kept (copy it if its buffer is reused).
    """

    def __init__(self, options: FeatureOptions, expected_shape: tuple[int, int] | None) -> None:
        self.options = options
        self.expected_shape = expected_shape  # the camera's own (height, width)
        self.tracker = FeatureTracker(options) if options.track_between else None

    @property
    def in_order(self) -> bool:
        return self.tracker is not None

    def __call__(self, image: np.ndarray, t_ns: int) -> FrameFeatures:
        if self.tracker is None:
            return extract_features(image, t_ns, self.options, self.expected_shape)
        return self.tracker.features(image, t_ns, self.expected_shape)
