"""Feature tracks over a short window of frames, for the visual-inertial start.

Each frame's features are matched to the live tracks, those seen in one of the last
``max_gap_frames`` frames (a detector misses a feature now and then; a track that died at
every miss would be too short to give parallax): the nearest descriptor within ``search_px``
(per frame since the track was last seen) of where it was, unambiguous (ratio test), close
enough in descriptor space and the mutual best. An essential matrix fitted by RANSAC to the
matches with the previous frame drops those that break the epipolar geometry (a repeated
texture matched to the wrong copy). A match continues the track; an unmatched feature starts
a new one. Only the last ``max_frames`` frames are kept.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from vtolpose.estimator.vision.association import AssociationOptions
from vtolpose.estimator.vision.camera_model import CameraModel
from vtolpose.estimator.vision.features import FrameFeatures, descriptor_distances


@dataclass(frozen=True, slots=True)
class TrackOptions:
    max_frames: int = 24
    search_px: float = 120.0  # a feature moves less than this between frames
    ratio_test: float = 0.8
    epipolar_px: float = 2.0  # RANSAC threshold of the essential-matrix check, in pixels
    max_features: int = 400  # strongest features per frame taken into tracks
    max_gap_frames: int = 3  # a track not seen for more frames than this is over
    min_matches_for_flow: int = 8


@dataclass(frozen=True, slots=True)
class TrackedFrame:
    """One frame of the window: its features' track ids, undistorted normalised points and pixels."""

    t_ns: int
    track_ids: np.ndarray  # (N,) int64
    xn: np.ndarray  # (N, 2) normalised image coordinates (undistorted)
    uv: np.ndarray  # (N, 2) pixels
    descriptors: np.ndarray  # (N, D)
    binary: bool
    flow_px: float = float("nan")  # median image motion of the features matched to the previous frame


class FeatureTracker:
    """Feed frames in time order; :attr:`frames` holds the window with track ids."""

    def __init__(self, camera: CameraModel, options: TrackOptions | None = None,
                 association: AssociationOptions | None = None) -> None:
        self.camera = camera
        self.options = options or TrackOptions()
        self.association = association or AssociationOptions()
        self.frames: deque[TrackedFrame] = deque(maxlen=self.options.max_frames)
        self._next_id = 0
        self._live: TrackedFrame | None = None  # the live tracks' last observations; ``flow_px`` holds no meaning
        self._age = np.zeros(0, dtype=np.int64)  # frames since each live track was seen

    def clear(self) -> None:
        self.frames.clear()
        self._live = None
        self._age = np.zeros(0, dtype=np.int64)

    def image_moving(self, t_ns: int, within_s: float, flow_px: float) -> bool:
        """Whether the scene moved more than ``flow_px`` within the last ``within_s`` before ``t_ns``: from one frame
        to the next, or over the frames of that span (the features tracked from its first frame to its last). A
        hover's wander moves the image half a pixel a frame, inside the features' noise from frame to frame, but
        steadily: ten pixels over the span, where a vehicle at rest moves no more than from frame to frame."""
        recent = [f for f in self.frames if 0 <= (t_ns - f.t_ns) * 1e-9 <= within_s]
        if any(f.flow_px > flow_px for f in recent):
            return True
        return len(recent) >= 2 and self._displacement_px(recent[0], recent[-1]) > flow_px

    def _displacement_px(self, first: TrackedFrame, last: TrackedFrame) -> float:
        """Median image motion of the features tracked from ``first`` to ``last`` (NaN if too few were)."""
        _, a, b = np.intersect1d(first.track_ids, last.track_ids, return_indices=True)
        if len(a) < self.options.min_matches_for_flow:
            return float("nan")
        return float(np.median(np.linalg.norm(last.uv[b] - first.uv[a], axis=1)))

    def add(self, features: FrameFeatures) -> TrackedFrame:
        """Match ``features`` to the live tracks, extend or start tracks, keep the frame."""
        n = min(len(features), self.options.max_features)
        uv = features.keypoints[:n]
        desc = features.descriptors[:n]
        xn = self.camera.undistort(uv) if n else np.zeros((0, 2))
        ids = np.full(n, -1, dtype=np.int64)
        flow = float("nan")
        live = self._live
        if live is not None and n and len(live.uv) and live.binary == features.binary \
                and live.descriptors.shape[1:] == desc.shape[1:]:
            old, new = self._match(live, self._age, uv, desc, features.binary)
            recent = self._age[old] == 0
            keep = np.ones(len(old), dtype=bool)
            if np.any(recent):
                keep[recent] = self._epipolar_inliers(live.xn[old[recent]], xn[new[recent]])
            ids[new[keep]] = live.track_ids[old[keep]]
            moved = recent & keep
            if np.sum(moved) >= self.options.min_matches_for_flow:
                flow = float(np.median(np.linalg.norm(uv[new[moved]] - live.uv[old[moved]], axis=1)))
        fresh = ids < 0
        ids[fresh] = np.arange(self._next_id, self._next_id + int(fresh.sum()))
        self._next_id += int(fresh.sum())
        frame = TrackedFrame(features.t_ns, ids, xn, uv.copy(), desc.copy(), features.binary, flow)
        self.frames.append(frame)
        self._keep_live(frame)
        return frame

    def _keep_live(self, frame: TrackedFrame) -> None:
        """The frame's features are live now; the other live tracks age by one frame, the oldest end."""
        live = self._live
        if live is None or live.binary != frame.binary or live.descriptors.shape[1:] != frame.descriptors.shape[1:]:
            self._live, self._age = frame, np.zeros(len(frame.track_ids), dtype=np.int64)
            return
        older = ~np.isin(live.track_ids, frame.track_ids) & (self._age + 1 <= self.options.max_gap_frames)
        self._live = TrackedFrame(frame.t_ns, np.concatenate([frame.track_ids, live.track_ids[older]]),
                                  np.vstack([frame.xn, live.xn[older]]), np.vstack([frame.uv, live.uv[older]]),
                                  np.vstack([frame.descriptors, live.descriptors[older]]), frame.binary)
        self._age = np.concatenate([np.zeros(len(frame.track_ids), dtype=np.int64), self._age[older] + 1])

    def _match(self, live: TrackedFrame, age: np.ndarray, uv: np.ndarray, desc: np.ndarray,
               binary: bool) -> tuple[np.ndarray, np.ndarray]:
        """Indices (live, new) of mutual, unambiguous descriptor matches within the search radius."""
        diff = live.uv[:, None, :] - uv[None, :, :]
        radius = self.options.search_px * (age + 1.0)
        near = np.einsum("onk,onk->on", diff, diff) <= (radius**2)[:, None]
        dist = np.where(near, descriptor_distances(live.descriptors, desc, binary), np.inf)
        limit = self.association.max_hamming_fraction if binary else self.association.max_descriptor_distance
        best_new = np.argmin(dist, axis=1)
        best_old = np.argmin(dist, axis=0)
        rows = np.arange(len(live.uv))
        best = dist[rows, best_new]
        second = np.partition(dist, 1, axis=1)[:, 1] if dist.shape[1] >= 2 else np.full(len(rows), np.inf)
        ok = np.isfinite(best) & (best <= limit) & (best < self.options.ratio_test * second)
        ok &= best_old[best_new] == rows  # mutual
        return rows[ok], best_new[ok]

    def _epipolar_inliers(self, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
        """Matches consistent with one essential matrix (all of them when too few to test)."""
        if len(x0) < 8:
            return np.ones(len(x0), dtype=bool)
        import cv2  # on first use: a process that never needs OpenCV never loads it (~16 MB)

        threshold = self.options.epipolar_px / max(self.camera.fx, self.camera.fy)
        try:
            E, mask = cv2.findEssentialMat(x0.astype(np.float64), x1.astype(np.float64), np.eye(3),
                                           method=cv2.RANSAC, prob=0.999, threshold=threshold)
        except cv2.error:  # a degenerate sample (no motion: OpenCV ≥ 5.1's solver refuses it) tests nothing
            return np.ones(len(x0), dtype=bool)
        if E is None or mask is None:
            return np.ones(len(x0), dtype=bool)
        return mask.ravel().astype(bool)
