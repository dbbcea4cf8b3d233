"""Data association: which feature of this frame is which landmark of the map (spec section).

For every landmark predicted inside the image: the features within a fixed pixel radius of
the prediction are candidates (thesis: 100 px); the best descriptor match among them must pass
Lowe's ratio test against the second best and an absolute distance limit; a feature goes to at
most one landmark (the closer descriptor wins); finally the innovation must pass the χ² test
``εᵀ S⁻¹ ε ≤ λ`` (2 dof, λ = 5.99 at 95 %). Every landmark that was predicted in view and not
matched is counted with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vtolpose.estimator.vision.camera_update import Predictions
from vtolpose.estimator.vision.features import FrameFeatures, descriptor_distances

REASONS = ("no_feature_in_gate", "descriptor_distance", "ratio_test", "feature_taken", "chi2", "singular_S")


@dataclass(frozen=True, slots=True)
class AssociationOptions:
    gate_px: float = 100.0
    ratio_test: float = 0.8  # best distance must be below this fraction of the second best
    max_descriptor_distance: float = 0.6  # float descriptors (unit L2), in [0, 2]
    max_hamming_fraction: float = 0.3  # binary descriptors, fraction of differing bits
    chi2: float = 5.99


@dataclass(slots=True)
class Association:
    """Accepted matches (landmark index → feature index) and the reasons for the rest."""

    landmark: np.ndarray
    feature: np.ndarray
    nis: np.ndarray
    candidates: int = 0  # landmarks predicted inside the image
    rejected: dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.landmark)


def _reject(rejected: dict[str, int], reason: str, n: int) -> None:
    if n:
        rejected[reason] = rejected.get(reason, 0) + int(n)


def associate(
    predictions: Predictions, landmark_descriptors: np.ndarray, features: FrameFeatures, options: AssociationOptions
) -> Association:
    """Match the map's visible landmarks to ``features``; returns the accepted pairs."""
    visible = np.flatnonzero(predictions.in_image)
    rejected: dict[str, int] = {}
    empty = Association(np.zeros(0, int), np.zeros(0, int), np.zeros(0), len(visible), rejected)
    if len(visible) == 0:
        return empty
    if len(features) == 0 or landmark_descriptors.shape[1] != features.descriptors.shape[1]:
        _reject(rejected, "no_feature_in_gate", len(visible))
        return empty
    uv = predictions.uv[visible]
    diff = uv[:, None, :] - features.keypoints[None, :, :]
    in_gate = np.einsum("vnk,vnk->vn", diff, diff) <= options.gate_px**2
    dist = descriptor_distances(landmark_descriptors[visible], features.descriptors, features.binary)
    dist = np.where(in_gate, dist, np.inf)
    limit = options.max_hamming_fraction if features.binary else options.max_descriptor_distance
    if dist.shape[1] >= 2:
        two = np.partition(dist, 1, axis=1)[:, :2]
        best_d, second_d = two[:, 0], two[:, 1]
    else:
        best_d, second_d = dist[:, 0], np.full(len(visible), np.inf)
    best = np.argmin(dist, axis=1)
    no_candidate = ~np.isfinite(best_d)
    too_far = ~no_candidate & (best_d > limit)
    ambiguous = ~no_candidate & ~too_far & np.isfinite(second_d) & (best_d >= options.ratio_test * second_d)
    _reject(rejected, "no_feature_in_gate", np.sum(no_candidate))
    _reject(rejected, "descriptor_distance", np.sum(too_far))
    _reject(rejected, "ratio_test", np.sum(ambiguous))
    ok = np.flatnonzero(~(no_candidate | too_far | ambiguous))
    # One feature, one landmark: the closest descriptor keeps it.
    order = ok[np.argsort(best_d[ok], kind="stable")]
    taken: set[int] = set()
    keep = []
    for v in order:
        f = int(best[v])
        if f in taken:
            continue
        taken.add(f)
        keep.append(v)
    _reject(rejected, "feature_taken", len(ok) - len(keep))
    keep = np.array(sorted(keep), dtype=int)
    if len(keep) == 0:
        return empty
    lm = visible[keep]
    feat = best[keep]
    eps = features.keypoints[feat] - predictions.uv[lm]
    S = predictions.S[lm]
    det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
    good_s = np.isfinite(det) & (det > 0.0) & (S[:, 0, 0] > 0.0)
    _reject(rejected, "singular_S", np.sum(~good_s))
    safe_det = np.where(good_s, det, 1.0)
    nis = (S[:, 1, 1] * eps[:, 0] ** 2 - 2.0 * S[:, 0, 1] * eps[:, 0] * eps[:, 1] + S[:, 0, 0] * eps[:, 1] ** 2) / safe_det
    passed = good_s & (nis <= options.chi2)
    _reject(rejected, "chi2", np.sum(good_s & ~passed))
    return Association(lm[passed], feat[passed], nis[passed], len(visible), rejected)
