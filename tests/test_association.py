"""Data association on synthetic predictions and features: every rule and every rejection reason."""

from __future__ import annotations

import numpy as np
import pytest

from vtolpose.estimator.vision.association import AssociationOptions, associate
from vtolpose.estimator.vision.camera_update import Predictions
from vtolpose.estimator.vision.features import FrameFeatures, descriptor_distances


def unit_rows(n: int, seed: int, dim: int = 128) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, dim)).astype(np.float32)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def predictions(uv: np.ndarray, sigma_px: float = 3.0, in_image: np.ndarray | None = None) -> Predictions:
    m = len(uv)
    S = np.tile(np.eye(2) * sigma_px**2, (m, 1, 1))
    inside = np.ones(m, dtype=bool) if in_image is None else in_image
    zeros = np.zeros((m, 2, 6))
    return Predictions(np.asarray(uv, float), np.zeros((m, 3)), np.ones(m, bool), inside, zeros, zeros, S)


def frame(keypoints, descriptors, binary=False) -> FrameFeatures:
    kp = np.asarray(keypoints, dtype=float).reshape(-1, 2)
    return FrameFeatures(0, kp, descriptors, np.arange(len(kp), 0, -1, dtype=float), (494, 656), binary=binary)


def noisy(desc: np.ndarray, amount: float, seed: int) -> np.ndarray:
    out = desc + amount * unit_rows(len(desc), seed, desc.shape[1])
    return (out / np.linalg.norm(out, axis=1, keepdims=True)).astype(np.float32)


def test_true_matches_are_found_among_distractors():
    lm_desc = unit_rows(5, 0)
    pred_uv = np.array([[100, 100], [300, 200], [500, 400], [200, 400], [600, 50]], float)
    true_uv = pred_uv + np.array([[2, -1], [-3, 2], [1, 1], [0, -2], [-1, 3]])
    distract_uv = pred_uv + 40.0
    feats = frame(np.vstack([distract_uv, true_uv]), np.vstack([unit_rows(5, 9), noisy(lm_desc, 0.2, 1)]))
    out = associate(predictions(pred_uv), lm_desc, feats, AssociationOptions())
    assert out.landmark.tolist() == [0, 1, 2, 3, 4]
    assert out.feature.tolist() == [5, 6, 7, 8, 9]
    assert out.candidates == 5 and out.rejected == {}
    assert np.all(out.nis <= 5.99)


def test_each_rejection_reason_is_counted():
    lm_desc = unit_rows(6, 1)
    pred_uv = np.array([[100, 100], [300, 100], [500, 100], [100, 300], [300, 300], [308, 300]], float)
    kp, desc = [], []
    kp.append([100 + 150, 100])  # 0: its twin lies outside the 100 px gate
    desc.append(lm_desc[0])
    kp.append([302, 101])  # 1: a feature inside the gate, but a different point
    desc.append(unit_rows(1, 50)[0])
    kp += [[498, 100], [503, 102]]  # 2: two equally good candidates -> ratio test
    desc += [noisy(lm_desc[2:3], 0.25, 2)[0], noisy(lm_desc[2:3], 0.25, 3)[0]]
    kp.append([100, 330])  # 3: right descriptor, but 30 px off with a 3 px prediction sigma -> chi2
    desc.append(lm_desc[3])
    kp.append([302, 301])  # 4 and 5 share one feature: the closer descriptor wins
    desc.append(noisy(lm_desc[4:5], 0.05, 4)[0])
    lm_desc[5] = noisy(lm_desc[4:5], 0.3, 5)[0]
    out = associate(predictions(pred_uv), lm_desc, frame(kp, np.array(desc)), AssociationOptions())
    assert out.landmark.tolist() == [4]
    assert out.rejected == {"no_feature_in_gate": 1, "descriptor_distance": 1, "ratio_test": 1, "chi2": 1, "feature_taken": 1}
    assert sum(out.rejected.values()) + len(out) == out.candidates == 6


def test_landmarks_out_of_view_are_not_candidates_and_no_features_is_safe():
    lm_desc = unit_rows(3, 2)
    pred = predictions(np.array([[10.0, 10.0], [np.nan, np.nan], [700.0, 10.0]]), in_image=np.array([True, False, False]))
    out = associate(pred, lm_desc, frame(np.zeros((0, 2)), np.zeros((0, 128), np.float32)), AssociationOptions())
    assert out.candidates == 1 and len(out) == 0 and out.rejected == {"no_feature_in_gate": 1}


def test_singular_innovation_covariance_is_rejected_and_counted():
    lm_desc = unit_rows(2, 3)
    pred = predictions(np.array([[100.0, 100.0], [300.0, 300.0]]))
    S = pred.S.copy()
    S[0] = 0.0
    S[1] = np.nan
    pred = Predictions(pred.uv, pred.h_c, pred.in_front, pred.in_image, pred.H_pose, pred.H_landmark, S)
    out = associate(pred, lm_desc, frame([[101, 100], [300, 301]], lm_desc.copy()), AssociationOptions())
    assert len(out) == 0 and out.rejected == {"singular_S": 2}


def test_binary_descriptors_use_the_bit_fraction():
    rng = np.random.default_rng(4)
    lm = rng.integers(0, 256, size=(2, 32), dtype=np.uint8)
    close = lm.copy()
    close[:, :2] ^= 0b00000111  # 6 bits of 256 differ
    far = rng.integers(0, 256, size=(2, 32), dtype=np.uint8)
    d = descriptor_distances(lm, np.vstack([close, far]), binary=True)
    np.testing.assert_allclose(np.diag(d[:, :2]), 6 / 256)
    assert np.all(d[:, 2:] > 0.3)
    pred = predictions(np.array([[100.0, 100.0], [400.0, 300.0]]))
    out = associate(pred, lm, frame([[101, 99], [399, 301]], close, binary=True), AssociationOptions())
    assert out.landmark.tolist() == [0, 1]


@pytest.mark.parametrize("ratio, accepted", [(0.8, False), (0.99, True)])
def test_ratio_threshold_is_honoured(ratio, accepted):
    lm = unit_rows(1, 6)
    best, second = noisy(lm, 0.3, 7), noisy(lm, 0.34, 8)
    out = associate(predictions(np.array([[200.0, 200.0]])), lm,
                    frame([[200, 201], [230, 200]], np.vstack([best, second])), AssociationOptions(ratio_test=ratio))
    assert (len(out) == 1) is accepted
