"""Map management for short-time EKF-SLAM: which landmarks live, which are born (spec section).

A landmark dies when it has been predicted inside the image but not matched for ``stale_frames``
frames in a row, when it has been out of view for ``out_of_view_frames`` frames, or when its
match ratio (matched / predicted in view) falls below ``min_match_ratio``. The map is capped
at ``max_landmarks`` (EKF-SLAM costs O(n²) per update). New landmarks come from unmatched
features spread over the image (at least ``min_feature_distance_px`` from every prediction and
from each other), strongest first, while fewer than ``target_in_view`` landmarks are in view.

The inverse-depth prior of a new landmark, best source first: the height above the ground
along its ray when the position is absolute (GPS) and the ground level is known; the median
depth of the well-observed landmarks in view; Civera's ρ0 = 0.1 m⁻¹. Civera's σ_ρ = 0.5 m⁻¹ puts
the 95 % region at depths beyond 0.9 m, which leaves the book rig's table (0.5–1 m away, ρ ≈ 1.3)
2.5 σ out, where the χ² gate rejects its matches before the depth can converge; σ_ρ = 1 m⁻¹
still reaches infinity and covers depths from 0.5 m.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vtolpose.estimator.vision.features import FrameFeatures
from vtolpose.estimator.vision.landmarks import landmark_points
from vtolpose.estimator.core.state import FilterState

DELETE_REASONS = ("non_finite", "behind_camera", "stale", "out_of_view", "match_ratio")  # by priority


@dataclass(frozen=True, slots=True)
class MapOptions:
    max_landmarks: int = 60
    target_in_view: int = 30
    max_new_per_frame: int = 12
    stale_frames: int = 4
    out_of_view_frames: int = 8
    min_match_ratio: float = 0.4
    min_predictions_for_ratio: int = 8
    min_feature_distance_px: float = 30.0
    border_px: float = 12.0
    rho0: float = 0.1  # m⁻¹, Civera et al.
    sigma_rho: float = 1.0  # m⁻¹ (Civera: 0.5; doubled so that 95 % also covers depths down to 0.5 m)
    depth_sigma_rel: float = 0.5  # σ_ρ / ρ0 when the depth comes from the height or the map
    converged_sigma_rel: float = 0.15  # σ_ρ / ρ below which a landmark's depth is good enough to seed new ones
    depth_known_sigma_rel: float = 0.3  # σ_ρ / ρ below which a landmark's depth counts as observed ...
    depth_known_shrink: float = 0.5  # ... once σ_ρ has also shrunk below this fraction of its initial value
    depth_known_frames: int = 3  # ... and both have held in this many frames in which it was matched
    min_baseline_chi2: float = 9.0  # a guessed depth moves only once the baseline exceeds 3 of its sigmas
    guessed_iterations: int = 4  # iterated-EKF steps for the matches of guessed-depth landmarks
    ground_down_m: float | None = 0.0  # world down of the ground under the vehicle; None: unknown
    min_height_m: float = 0.1  # below this height above ground the height prior is not used
    min_ray_down: float = 0.3  # rays flatter than this (down component of the unit ray) get no height prior


class LandmarkBook:
    """What the filter state does not hold about each landmark, in the same row order."""

    def __init__(self) -> None:
        self.ids = np.zeros(0, dtype=np.int64)
        self.descriptors: np.ndarray | None = None
        self.predicted = np.zeros(0, dtype=np.int64)  # frames in which it was predicted in view
        self.matched = np.zeros(0, dtype=np.int64)
        self.misses = np.zeros(0, dtype=np.int64)  # consecutive in-view frames without a match
        self.unseen = np.zeros(0, dtype=np.int64)  # consecutive frames out of view
        self.sigma_rho0 = np.zeros(0)  # inverse-depth σ at birth
        self.settled = np.zeros(0, dtype=np.int64)  # matched frames in a row with a small σ_ρ
        self.next_id = 0

    def __len__(self) -> int:
        return len(self.ids)

    def clear(self) -> None:
        keep_next = self.next_id
        self.__init__()
        self.next_id = keep_next

    def append(self, descriptors: np.ndarray, sigma_rho0: np.ndarray) -> np.ndarray:
        k = len(descriptors)
        new_ids = np.arange(self.next_id, self.next_id + k, dtype=np.int64)
        self.next_id += k
        self.ids = np.concatenate([self.ids, new_ids])
        if self.descriptors is None or len(self.descriptors) == 0:
            self.descriptors = descriptors.copy()
        else:
            self.descriptors = np.vstack([self.descriptors, descriptors])
        zeros = np.zeros(k, dtype=np.int64)
        self.predicted = np.concatenate([self.predicted, zeros])
        self.matched = np.concatenate([self.matched, zeros])
        self.misses = np.concatenate([self.misses, zeros])
        self.unseen = np.concatenate([self.unseen, zeros])
        self.sigma_rho0 = np.concatenate([self.sigma_rho0, np.broadcast_to(sigma_rho0, (k,))])
        self.settled = np.concatenate([self.settled, zeros])
        return new_ids

    def keep(self, mask: np.ndarray) -> None:
        for name in ("ids", "predicted", "matched", "misses", "unseen", "sigma_rho0", "settled"):
            setattr(self, name, getattr(self, name)[mask])
        if self.descriptors is not None:
            self.descriptors = self.descriptors[mask]

    def record(self, in_view: np.ndarray, matched: np.ndarray) -> None:
        """Count this frame: ``in_view`` and ``matched`` are boolean masks over the landmarks."""
        self.predicted += in_view
        self.matched += matched
        self.misses = np.where(matched, 0, np.where(in_view, self.misses + 1, self.misses))
        self.unseen = np.where(in_view, 0, self.unseen + 1)


def deletions(book: LandmarkBook, state: FilterState, in_front: np.ndarray, options: MapOptions) -> dict[str, np.ndarray]:
    """Masks of the landmarks to delete, by reason (a landmark is listed under its first reason)."""
    finite = np.all(np.isfinite(state.landmarks), axis=1)
    ratio_known = book.predicted >= options.min_predictions_for_ratio
    ratio = book.matched / np.maximum(book.predicted, 1)
    tests = {
        "non_finite": ~finite,
        "behind_camera": ~in_front & (book.unseen >= options.out_of_view_frames),
        "stale": book.misses >= options.stale_frames,
        "out_of_view": book.unseen >= options.out_of_view_frames,
        "match_ratio": ratio_known & (ratio < options.min_match_ratio),
    }
    taken = np.zeros(len(book), dtype=bool)
    out = {}
    for reason in DELETE_REASONS:
        mask = tests[reason] & ~taken
        taken |= mask
        out[reason] = mask
    return out


def depth_small(book: LandmarkBook, state: FilterState, rows: np.ndarray, sigma_rel: float, shrink: float) -> np.ndarray:
    """Landmarks (by row) whose inverse-depth σ is small relative to ρ and to its σ at birth."""
    rows = np.asarray(rows, dtype=int)
    index = state.map_start + 6 * rows + 5
    rho = state.landmarks[rows, 5]
    sigma = np.sqrt(np.maximum(state.cov[index, index], 0.0))
    return (rho > 0.0) & (sigma < sigma_rel * rho) & (sigma < shrink * book.sigma_rho0[rows])


def depth_known(book: LandmarkBook, state: FilterState, rows: np.ndarray, options: MapOptions) -> np.ndarray:
    """Landmarks (by row) whose depth has been observed, not just guessed.

    A small σ_ρ alone is not enough: one update with a wrong baseline (the measurement is
    bilinear in ρ and the camera centre) can throw ρ far out *and* shrink its σ. Such a landmark
    fails its next χ² tests; a truly observed one keeps being matched, so the small σ must have
    held over ``depth_known_frames`` matched frames.
    """
    rows = np.asarray(rows, dtype=int)
    small = depth_small(book, state, rows, options.depth_known_sigma_rel, options.depth_known_shrink)
    return small & (book.settled[rows] >= options.depth_known_frames)


def record_settling(book: LandmarkBook, state: FilterState, matched_rows: np.ndarray, options: MapOptions) -> None:
    """After an update: matched landmarks with a small σ_ρ count one more settled frame; others restart."""
    rows = np.arange(len(book))
    small = depth_small(book, state, rows, options.depth_known_sigma_rel, options.depth_known_shrink)
    matched = np.zeros(len(book), dtype=bool)
    matched[matched_rows] = True
    book.settled = np.where(small, book.settled + matched, 0)


def select_new_features(
    features: FrameFeatures,
    occupied_uv: np.ndarray,
    used_features: np.ndarray,
    n_max: int,
    min_distance_px: float,
    border_px: float,
) -> np.ndarray:
    """Indices of unmatched features for new landmarks: spread out, strongest first.

    ``features`` are sorted by response already. A feature is taken when it is inside the
    image by ``border_px`` and at least ``min_distance_px`` from every occupied pixel (the
    predictions of existing landmarks and the features chosen before it).
    """
    if n_max <= 0 or len(features) == 0:
        return np.zeros(0, dtype=int)
    h, w = features.image_shape
    kp = features.keypoints
    free = np.ones(len(kp), dtype=bool)
    free[used_features] = False
    free &= (kp[:, 0] >= border_px) & (kp[:, 0] <= w - 1 - border_px) & (kp[:, 1] >= border_px) & (kp[:, 1] <= h - 1 - border_px)
    limit = min_distance_px**2
    occupied = occupied_uv[np.all(np.isfinite(occupied_uv), axis=1)] if len(occupied_uv) else np.zeros((0, 2))
    if len(occupied):  # the free features' squared distances to their nearest occupied pixel
        candidates = np.flatnonzero(free)
        du = kp[candidates, 0, None] - occupied[None, :, 0]
        dv = kp[candidates, 1, None] - occupied[None, :, 1]
        free[candidates] = np.min(du * du + dv * dv, axis=1) >= limit
    chosen: list[int] = []
    for i in np.flatnonzero(free):
        if chosen:
            d = kp[chosen] - kp[i]
            if np.min(np.einsum("ij,ij->i", d, d)) < limit:
                continue
        chosen.append(int(i))
        if len(chosen) == n_max:
            break
    return np.array(chosen, dtype=int)


def scene_depth(
    book: LandmarkBook, state: FilterState, R_WC: np.ndarray, c_w: np.ndarray, in_view: np.ndarray, options: MapOptions
) -> tuple[float, int] | None:
    """Depth (along the optical axis) of the well-observed landmark in view at the median depth, and its
    row; None without three of them. The new landmarks' prior is read off that one landmark, so that
    it can be taken as a function of the state (no new information), not as an independent guess."""
    idx = np.flatnonzero(in_view)
    if len(idx) == 0:
        return None
    good = idx[depth_known(book, state, idx, options)]
    good = good[depth_small(book, state, good, options.converged_sigma_rel, options.depth_known_shrink)]
    if len(good) < 3:
        return None
    depth = (landmark_points(state.landmarks[good]) - c_w) @ R_WC[:, 2]
    good, depth = good[depth > 0.0], depth[depth > 0.0]
    if len(depth) < 3:
        return None
    middle = int(np.argsort(depth)[len(depth) // 2])
    return float(depth[middle]), int(good[middle])


def depth_priors(
    rays_w: np.ndarray,
    rays_c: np.ndarray,
    c_w: np.ndarray,
    absolute_position: bool,
    depth_along_axis: float | None,
    options: MapOptions,
) -> tuple[np.ndarray, np.ndarray, str]:
    """Inverse depth and its σ for new landmarks along unit world rays; and which source gave it."""
    k = len(rays_w)
    height = None if options.ground_down_m is None else options.ground_down_m - float(c_w[2])
    if absolute_position and height is not None and height > options.min_height_m:
        down = rays_w[:, 2]
        ok = down > options.min_ray_down
        rho = np.where(ok, np.maximum(down, 1e-9) / height, options.rho0)
        sigma = np.where(ok, options.depth_sigma_rel * rho, options.sigma_rho)
        return rho, sigma, "height"
    if depth_along_axis is not None:
        # A ray [x, y, 1] in the camera reaches the depth plane z = d at distance d·|[x, y, 1]|.
        rho = 1.0 / (depth_along_axis * np.linalg.norm(rays_c, axis=1))
        return rho, options.depth_sigma_rel * rho, "map"
    return np.full(k, options.rho0), np.full(k, options.sigma_rho), "civera"
