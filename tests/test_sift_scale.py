"""SIFT on the halved frame (features.sift_image_scale): keypoints where the features are, in full-frame pixels."""

from __future__ import annotations

import numpy as np
import pytest

from vtolpose.config import ConfigError, load_config
from vtolpose.estimator.vision.features import FeatureOptions, descriptor_distances, extract_features

H, W = 494, 656


def blobs(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A frame of 35 bright Gaussian blobs (sigma 3-5 px) at known sub-pixel centres, with sensor noise."""
    rng = np.random.default_rng(seed)
    centres = np.array([[60 + 90 * i + rng.uniform(0, 1), 60 + 90 * j + rng.uniform(0, 1)]
                        for i in range(7) for j in range(5)])
    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    image = np.full((H, W), 60.0)
    for k, (cx, cy) in enumerate(centres):
        sigma = 3.0 + k % 3
        image += 150 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma**2))
    return np.clip(image + rng.normal(0, 1.0, image.shape), 0, 255).astype(np.uint8), centres


def texture(seed: int) -> np.ndarray:
    """Smooth random texture, larger than the frame so that shifted views of it can be cut out."""
    import cv2

    noise = np.random.default_rng(seed).normal(size=((H + 64) // 4, (W + 64) // 4)).astype(np.float32)
    img = cv2.resize(noise, (W + 64, H + 64), interpolation=cv2.INTER_CUBIC)
    return np.clip(128 + 40 * img / img.std(), 0, 255).astype(np.uint8)


def test_halved_sift_puts_every_blob_where_it_is():
    image, centres = blobs()
    features = extract_features(image, 0, FeatureOptions())  # the default: sift at scale 0.5
    assert FeatureOptions().sift_image_scale == 0.5
    d = np.linalg.norm(centres[:, None] - features.keypoints[None], axis=2)
    nearest = d.argmin(axis=1)
    assert np.all(d.min(axis=1) < 0.5), d.min(axis=1)
    # No systematic offset: a mapping from the small image off by half a pixel would show here.
    assert np.all(np.abs(np.mean(features.keypoints[nearest] - centres, axis=0)) < 0.1)


def test_the_full_pyramid_is_still_there_and_finds_the_same_blobs():
    image, centres = blobs()
    full = extract_features(image, 0, FeatureOptions(sift_image_scale=1.0))
    half = extract_features(image, 0, FeatureOptions())
    for features in (full, half):
        assert np.all(np.linalg.norm(centres[:, None] - features.keypoints[None], axis=2).min(axis=1) < 1.0)
    assert full.descriptors.shape[1] == half.descriptors.shape[1] == 128


@pytest.mark.parametrize("scale", [0.5, 1.0])
def test_a_shifted_view_matches_with_the_shift(scale):
    """Two views 7 px right and 3 px down of each other: matched descriptors must sit exactly that far apart."""
    big = texture(11)
    first, second = big[10 : 10 + H, 20 : 20 + W], big[7 : 7 + H, 13 : 13 + W]
    options = FeatureOptions(sift_image_scale=scale)
    a, b = extract_features(first, 0, options), extract_features(second, 1, options)
    dist = descriptor_distances(a.descriptors, b.descriptors, a.binary)
    two = np.sort(dist, axis=1)[:, :2]
    good = (two[:, 0] < 0.6) & (two[:, 0] < 0.8 * two[:, 1])
    shift = b.keypoints[dist.argmin(axis=1)[good]] - a.keypoints[good]
    assert good.sum() >= 100
    on_shift = np.linalg.norm(shift - [7.0, 3.0], axis=1) < 0.5
    assert on_shift.mean() > 0.9
    assert np.all(np.abs(np.median(shift[on_shift], axis=0) - [7.0, 3.0]) < 0.1)


def test_other_detectors_ignore_the_sift_scale():
    image = texture(3)[:H, :W]
    for detector in ("orb",):
        a = extract_features(image, 0, FeatureOptions(detector=detector, sift_image_scale=0.5))
        b = extract_features(image, 0, FeatureOptions(detector=detector, sift_image_scale=1.0))
        assert np.array_equal(a.keypoints, b.keypoints) and np.array_equal(a.descriptors, b.descriptors)


def test_the_scale_is_bounded_in_options_and_config(tmp_path):
    with pytest.raises(ValueError, match="sift_image_scale"):
        FeatureOptions(sift_image_scale=0.1)
    path = tmp_path / "c.yaml"
    path.write_text("features:\n  sift_image_scale: 1.5\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"features\.sift_image_scale': must be at most 1"):
        load_config(path)
    assert load_config(None, {"features": {"sift_image_scale": 1.0}})["features.sift_image_scale"] == 1.0
