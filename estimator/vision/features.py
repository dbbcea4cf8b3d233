"""Point features of one frame: keypoints and descriptors through OpenCV.

SIFT is the thesis' choice (and the default); ORB is an order of magnitude cheaper; AKAZE is
offered where the OpenCV build has it (OpenCV 5 moved it to the contrib modules). The work is
one plain function of (image, options) with no shared state, so a daemon can run it in a
thread pool: OpenCV releases the GIL while it detects and describes.

Descriptors are normalised so that one distance scale serves every detector: float
descriptors (SIFT) to unit L2 norm, so distances lie in [0, 2]; binary descriptors (ORB,
AKAZE's MLDB) stay packed bits, compared by the fraction of differing bits in [0, 1].

SIFT's cost: OpenCV's SIFT doubles its input before building the scale space, so three
quarters of its work is an octave finer than the camera's pixels. ``sift_image_scale`` 0.5
hands it the frame halved (area averaging), so the pyramid starts at the frame's own
resolution: about a third of the work, the same descriptor, keypoints mapped back to
full-frame pixels. 1.0 is the thesis' full pyramid.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from vtolpose.estimator.vision.frame_quality import FrameQualityOptions, frame_problem
from vtolpose.estimator.core.calibration import working_size

if TYPE_CHECKING:
    import cv2

DETECTORS = ("sift", "orb", "akaze")


@dataclass(frozen=True, slots=True)
class FeatureOptions:
    detector: str = "sift"
    max_features: int = 400  # strongest responses kept per frame
    sift_contrast_threshold: float = 0.02  # lower than OpenCV's 0.04: aerial texture is soft
    orb_fast_threshold: int = 20
    sift_image_scale: float = 0.5  # SIFT sees the frame resized by this (1.0: the full, doubled pyramid)
    working_width: int = 0  # a wider frame is reduced to this before anything (working_frame); 0: as it is
    track_between: int = 0  # frames tracked by optical flow between two detections (0: detect every frame)
    min_tracked_fraction: float = 0.5  # detect again as soon as fewer of the last detection's points are tracked
    max_flow_error_px: float = 0.5  # forward–backward distance above which a tracked point is dropped
    quality: FrameQualityOptions = field(default_factory=FrameQualityOptions)

    def __post_init__(self) -> None:
        if self.detector not in DETECTORS:
            raise ValueError(f"unknown feature detector {self.detector!r}; choose one of {', '.join(DETECTORS)}")
        if self.max_features < 1:
            raise ValueError(f"max_features must be at least 1, got {self.max_features}")
        if self.track_between < 0:
            raise ValueError(f"track_between must be 0 (detect every frame) or more, got {self.track_between}")
        if not 0.0 <= self.min_tracked_fraction <= 1.0:
            raise ValueError(f"min_tracked_fraction must be in [0, 1], got {self.min_tracked_fraction}")
        if self.max_flow_error_px <= 0.0:
            raise ValueError(f"max_flow_error_px must be positive, got {self.max_flow_error_px}")
        if not 0.25 <= self.sift_image_scale <= 1.0:
            raise ValueError(f"sift_image_scale must be in [0.25, 1], got {self.sift_image_scale}")
        if self.detector == "akaze":
            import cv2

            if not hasattr(cv2, "AKAZE_create"):
                raise ValueError(f"detector 'akaze' is not in this OpenCV build ({cv2.__version__}); use sift or orb")


@dataclass(frozen=True, slots=True)
class FrameFeatures:
    """Features of the frame taken at ``t_ns``; ``problem`` names why a frame gave none."""

    t_ns: int
    keypoints: np.ndarray  # (N, 2) pixel coordinates, float64
    descriptors: np.ndarray  # (N, D): float32 unit vectors, or uint8 packed bits when ``binary``
    responses: np.ndarray  # (N,) detector response (strength)
    image_shape: tuple[int, int]
    binary: bool = False
    problem: str | None = None  # one of vtolpose.estimator.vision.frame_quality.PROBLEMS, or None
    digest: bytes = b""  # hash of the pixels: an identical frame twice is a duplicate
    extract_ms: float = 0.0  # wall time of the extraction
    extract_cpu_ms: float = 0.0  # CPU time of the extracting thread (one core's work, whatever the machine's load)

    def __len__(self) -> int:
        return len(self.keypoints)

    @classmethod
    def rejected(cls, t_ns: int, image_shape: tuple[int, ...], problem: str, digest: bytes = b"") -> "FrameFeatures":
        return cls(t_ns, np.zeros((0, 2)), np.zeros((0, 0), np.float32), np.zeros(0), tuple(image_shape[:2]),
                   problem=problem, digest=digest)


def _detector(options: FeatureOptions) -> cv2.Feature2D:
    import cv2  # on first use: a process that never needs OpenCV never loads it (~16 MB)

    if options.detector == "sift":
        return cv2.SIFT_create(nfeatures=options.max_features, contrastThreshold=options.sift_contrast_threshold)
    if options.detector == "orb":
        return cv2.ORB_create(nfeatures=options.max_features, fastThreshold=options.orb_fast_threshold)
    return cv2.AKAZE_create()


def _detect(image: np.ndarray, options: FeatureOptions) -> tuple[tuple, np.ndarray | None, np.ndarray | None]:
    """Keypoints and descriptors, and the (x, y) factor from the image the detector saw to the frame."""
    import cv2

    scale = options.sift_image_scale
    if options.detector != "sift" or scale == 1.0:
        return (*_detector(options).detectAndCompute(image, None), None)
    height, width = image.shape[:2]
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    # Precise upscaling puts the doubled image's pixel 2x on the input's x (the default doubling is
    # a quarter pixel off, half a frame pixel once halved).
    sift = cv2.SIFT_create(nfeatures=options.max_features, contrastThreshold=options.sift_contrast_threshold,
                           enable_precise_upscale=True)
    keypoints, descriptors = sift.detectAndCompute(small, None)
    return keypoints, descriptors, np.array([width / size[0], height / size[1]])


def image_digest(image: np.ndarray) -> bytes:
    return hashlib.blake2b(np.ascontiguousarray(image).data, digest_size=16).digest()


def working_frame(image: np.ndarray, expected_shape: tuple[int, int] | None,
                  working_width: int) -> tuple[np.ndarray, tuple[int, int] | None]:
    """The frame reduced to the working width (INTER_AREA: each pixel the mean of those it covers), and the shape
    it must then have. A frame that is not the camera's size (``expected_shape``) is passed as it is, to be
    refused for it; one already at the working width is left alone.

    The camera pipeline then sees a 1280 x 720 camera as a 640 x 360 one (its intrinsics scaled the same way,
    ``CameraCalibration.working``): the same features at the same angles, the same pixel noise, every pixel
    threshold meaning the same angle. Found at full size, four times the keypoints each claimed twice as sharp
    took the real hand-held recording 300 m away (docs/results.md)."""
    if image.ndim != 2:
        return image, expected_shape
    height, width = image.shape
    if expected_shape is not None and (height, width) != tuple(expected_shape):
        return image, expected_shape
    w, h = working_size(width, height, working_width)
    if w == width:
        return image, expected_shape
    import cv2

    return cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA), (h, w)


def extract_features(
    image: np.ndarray, t_ns: int, options: FeatureOptions, expected_shape: tuple[int, int] | None = None
) -> FrameFeatures:
    """Quality check, then keypoints and descriptors of a grey uint8 image, strongest first; a frame wider than
    the working width is reduced to it first (:func:`working_frame`), and its keypoints are in its pixels."""
    started, started_cpu = time.perf_counter(), time.thread_time()
    image, expected_shape = working_frame(np.asarray(image), expected_shape, options.working_width)
    digest = image_digest(image) if image.size else b""
    problem = frame_problem(image, expected_shape, options.quality)
    if problem is not None:
        return FrameFeatures.rejected(t_ns, image.shape, problem, digest)
    keypoints, descriptors, to_frame = _detect(image, options)
    if descriptors is None or not keypoints:
        return FrameFeatures(t_ns, np.zeros((0, 2)), np.zeros((0, 0), np.float32), np.zeros(0), image.shape[:2],
                             binary=options.detector != "sift", digest=digest,
                             extract_ms=(time.perf_counter() - started) * 1e3,
                             extract_cpu_ms=(time.thread_time() - started_cpu) * 1e3)
    pts = np.array([k.pt for k in keypoints], dtype=float)
    if to_frame is not None:
        pts = (pts + 0.5) * to_frame - 0.5  # pixel centres of the resized image → the frame's
    responses = np.array([k.response for k in keypoints], dtype=float)
    order = np.argsort(-responses, kind="stable")[: options.max_features]
    binary = descriptors.dtype == np.uint8 and options.detector != "sift"
    if binary:
        desc = descriptors[order]
    else:
        desc = descriptors[order].astype(np.float32)
        desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
    return FrameFeatures(
        t_ns, pts[order], desc, responses[order], image.shape[:2], binary=binary, digest=digest,
        extract_ms=(time.perf_counter() - started) * 1e3, extract_cpu_ms=(time.thread_time() - started_cpu) * 1e3,
    )


def descriptor_distances(a: np.ndarray, b: np.ndarray, binary: bool) -> np.ndarray:
    """All distances between rows of ``a (M, D)`` and ``b (N, D)``: L2 of unit vectors, or bit fraction."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)))
    if binary:
        bits_a = np.unpackbits(a, axis=1).astype(np.float32)
        bits_b = np.unpackbits(b, axis=1).astype(np.float32)
        # Hamming = |a| + |b| − 2 a·b over 0/1 bits.
        ham = bits_a.sum(1)[:, None] + bits_b.sum(1)[None, :] - 2.0 * bits_a @ bits_b.T
        return np.maximum(ham, 0.0) / bits_a.shape[1]
    d2 = 2.0 - 2.0 * (a.astype(np.float32) @ b.astype(np.float32).T)
    return np.sqrt(np.maximum(d2, 0.0))
