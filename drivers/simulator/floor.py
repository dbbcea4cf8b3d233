"""The ``floor`` scenarios of the camera test matrix: a camera about 1.2 m over a textured floor.

Hand-held or hover scale: the platform holds a centre pose 1.2 m above a gently undulating floor
(a few centimetres, so the scene is not one exact plane) and moves by one of the named
:mod:`motion profiles <vtolpose.drivers.simulator.motion_profiles>`. The floor's look is a
parameter: a mosaic of real recorded frames (:mod:`.photo_mosaic`) or scikit-image's samples.

Starts (:func:`start_options`): ``rest`` (a still second, then the motion ramps in), ``motion``
(moving at full amplitude from the first sample), ``mid-flight`` (joined ``in_flight_s`` into the
trajectory: no rest and no stated heading).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vtolpose.drivers.simulator.gps_model import GpsErrorModel
from vtolpose.drivers.simulator.motion_profiles import PROFILES, MotionProfile
from vtolpose.drivers.simulator.photo_mosaic import PhotoSource, photo_mosaic
from vtolpose.drivers.simulator.textures import Appearance, TextureLayer, _mask
from vtolpose.drivers.simulator.trajectory import Trajectory

STARTS = ("rest", "motion", "mid-flight")


@dataclass
class FloorAppearance:
    """Two copies of one picture at different scales and angles, mixed by a smooth mask, so the floor's
    pattern does not repeat visibly within a camera's view."""

    layers: tuple[TextureLayer, TextureLayer]

    @classmethod
    def of(cls, photos: PhotoSource | None, texel_m: float = 0.002) -> "FloorAppearance":
        """A mosaic of ``photos``' frames; None: scikit-image's gravel and brick."""
        if photos is None:
            return cls((TextureLayer("gravel", texel_m), TextureLayer("brick", 1.6 * texel_m, 0.7, (91.0, 37.0))))
        image = photo_mosaic(photos)
        return cls((TextureLayer(photos.name, texel_m, image=image),
                    TextureLayer(photos.name, 1.55 * texel_m, 0.7, (311.0, 173.0), image=image)))

    def radiance(self, n: np.ndarray, e: np.ndarray, down: np.ndarray, footprint_m: float) -> np.ndarray:
        mix = _mask(n, e, (0.31, 0.43, 0.67))
        value = mix * self.layers[0].sample(n, e, footprint_m) + (1.0 - mix) * self.layers[1].sample(n, e, footprint_m)
        return (0.5 + 0.16 * value).astype(np.float32)


@dataclass(frozen=True, slots=True)
class FloorScenario:
    """A camera over a floor (down = 0 on average), moving by ``profile``; ``photos`` the floor's look."""

    profile: MotionProfile = field(default_factory=lambda: PROFILES["gentle"])
    photos: PhotoSource | None = None
    name: str = "floor"
    static_s: float = 1.0  # the still second of a start at rest; 0: moving from the first sample
    ramp_s: float = 2.0
    height_m: float = 1.2
    undulation_m: float = 0.03
    centre_euler: tuple[float, float, float] = (0.0, 0.0, 0.4)
    gps_sigma_h: float = 0.02  # an RTK-class receiver: anything coarser is blind at this scale
    origin_lla: tuple[float, float, float] | None = None
    heading_sigma_deg: float = 2.0  # lined up by eye with a mark on the floor
    in_flight_s: float = 30.0

    @property
    def description(self) -> str:
        look = self.photos.name if self.photos is not None else "scikit-image samples"
        return f"{self.profile.description}, {self.height_m:g} m over a floor textured with {look}"

    def ground_height(self, n: np.ndarray, e: np.ndarray) -> np.ndarray:
        """Down coordinate of the floor: 0 give or take ``undulation_m`` over metre-long waves."""
        n, e = np.asarray(n, dtype=float), np.asarray(e, dtype=float)
        a = self.undulation_m
        return a * np.sin(n / 0.27 + 0.4) * np.sin(e / 0.37 + 1.1) + 0.5 * a * np.sin((n + e) / 0.15)

    def trajectory(self, duration_s: float, gravity: float) -> Trajectory:
        """Endless; moving at full amplitude from t = 0 when there is no still start."""
        start = self.static_s if self.static_s > 0.0 else -self.ramp_s
        return self.profile.trajectory(np.array([0.0, 0.0, -self.height_m]), np.array(self.centre_euler), start, self.ramp_s)

    def gps_model(self) -> GpsErrorModel:
        return GpsErrorModel(sigma_h=self.gps_sigma_h)

    def appearance(self) -> Appearance:
        return FloorAppearance.of(self.photos)


def start_options(start: str, scenario: FloorScenario) -> dict[str, float]:
    """``SimulationOptions`` fields (``rest_s``, ``start_s``) for one of :data:`STARTS`."""
    if start == "rest":
        return {"rest_s": max(scenario.static_s, 1.0), "start_s": 0.0}
    if start == "motion":
        return {"rest_s": 0.0, "start_s": 0.0}
    if start == "mid-flight":
        return {"rest_s": scenario.static_s, "start_s": scenario.in_flight_s}
    raise ValueError(f"unknown start {start!r}; choose one of {list(STARTS)}")
