"""Is this frame worth extracting features from? A cheap check before the expensive one.

A black (lens cap, night), saturated (sun), textureless (fog, a wall too close, focus lost) or
wrong-size frame gives no features worth having, or worse, junk features made of noise; each
is a counted rejection with its own reason. The test runs on a 4× reduced image, which averages
sensor noise away, so "textureless" means no *scene* texture, not no noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PROBLEMS = ("wrong_size", "black", "saturated", "textureless", "unreadable")


@dataclass(frozen=True, slots=True)
class FrameQualityOptions:
    black_level: float = 12.0  # DN: a frame whose 99th percentile is below this is black
    saturated_level: int = 250  # DN: a pixel at or above this is saturated ...
    saturated_fraction: float = 0.6  # ... and a frame with more such pixels than this is saturated
    min_texture_std: float = 2.5  # DN: std of the 4x-reduced frame below this is textureless


def frame_problem(image: np.ndarray, expected_shape: tuple[int, int] | None, options: FrameQualityOptions) -> str | None:
    """The reason to reject ``image`` (one of :data:`PROBLEMS`), or None for a usable frame."""
    import cv2  # on first use: a process that never needs OpenCV never loads it (~16 MB)

    if image.ndim != 2 or image.dtype != np.uint8 or min(image.shape) < 8:
        return "wrong_size"
    if expected_shape is not None and tuple(image.shape) != tuple(expected_shape):
        return "wrong_size"
    small = cv2.resize(image, (image.shape[1] // 4, image.shape[0] // 4), interpolation=cv2.INTER_AREA)
    if np.percentile(small, 99) < options.black_level:
        return "black"
    if np.count_nonzero(small >= options.saturated_level) > options.saturated_fraction * small.size:
        return "saturated"
    if float(small.std()) < options.min_texture_std:
        return "textureless"
    return None
