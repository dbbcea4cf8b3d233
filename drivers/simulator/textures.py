"""What the simulated ground looks like: real photographs laid over the scenario's height field.

The photographs are scikit-image's bundled samples (gravel, grass, brick, a printed page; the
optional ``sim`` extra), so no download is needed. Each is a tile repeated over the ground at
a physical scale; two tiles of different scale and orientation, mixed by a smooth mask, keep
the pattern from repeating visibly. Tiles carry a mip chain: a camera far above a fine texture
sees its average, not aliasing noise that would change from frame to frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Protocol

import numpy as np


class Appearance(Protocol):
    def radiance(self, n: np.ndarray, e: np.ndarray, down: np.ndarray, footprint_m: float) -> np.ndarray:
        """Brightness in [0, 1] (float32) of the ground points (n, e, down) seen at ``footprint_m`` per pixel."""


@lru_cache(maxsize=8)
def photo(name: str) -> np.ndarray:
    """A scikit-image sample photograph, grey float32, mean 0, std 1."""
    import cv2  # on first use: a process that never needs OpenCV never loads it (~16 MB)

    try:
        from skimage import data
    except ImportError:  # pragma: no cover - depends on the installation
        raise ImportError("rendering camera frames needs scikit-image (pip install scikit-image; from a checkout: pip install -e '.[sim]')") from None
    image = getattr(data, name)()
    if image.ndim == 3:
        image = cv2.cvtColor(image[..., :3], cv2.COLOR_RGB2GRAY)
    image = image.astype(np.float32)
    return (image - image.mean()) / max(float(image.std()), 1e-6)


@dataclass
class TextureLayer:
    """A photograph laid on the ground, ``texel_m`` metres per texel, its columns along ``angle_rad``.

    Texture columns run along the ground direction (cos a, sin a) in (north, east), rows along
    (-sin a, cos a); rows may be stretched by ``aspect``. Ground (0, 0) sits at texel ``offset_px``.
    """

    name: str
    texel_m: float
    angle_rad: float = 0.0
    offset_px: tuple[float, float] = (0.0, 0.0)
    wrap: bool = True  # tile forever; False: one copy, 0 around it (a single printed page)
    aspect: float = 1.0
    image: np.ndarray | None = None  # the photograph itself (mean 0, std 1); None: scikit-image's ``name``

    def __post_init__(self) -> None:
        import cv2

        levels = [photo(self.name) if self.image is None else np.asarray(self.image, dtype=np.float32)]
        while min(levels[-1].shape) >= 16:
            h, w = levels[-1].shape
            levels.append(cv2.resize(levels[-1], (w // 2, h // 2), interpolation=cv2.INTER_AREA))
        self.levels = levels
        self.shape = levels[0].shape

    def sample(self, n: np.ndarray, e: np.ndarray, footprint_m: float) -> np.ndarray:
        """Texture values at ground points; blended between the two mip levels the footprint falls in."""
        level = min(max(math.log2(max(footprint_m, 1e-9) / self.texel_m), 0.0), len(self.levels) - 1.0)
        low = int(math.floor(level))
        frac = level - low
        out = self._at(n, e, low)
        if frac > 1e-3 and low + 1 < len(self.levels):
            out = (1.0 - frac) * out + frac * self._at(n, e, low + 1)
        return out

    def _at(self, n: np.ndarray, e: np.ndarray, level: int) -> np.ndarray:
        import cv2

        c, s = math.cos(self.angle_rad), math.sin(self.angle_rad)
        shrink = 2.0**level
        scale = 1.0 / (self.texel_m * shrink)
        col = ((c * n + s * e) * scale + self.offset_px[0] / shrink).astype(np.float32)
        row = ((c * e - s * n) * (scale / self.aspect) + self.offset_px[1] / shrink).astype(np.float32)
        border = cv2.BORDER_WRAP if self.wrap else cv2.BORDER_CONSTANT
        return cv2.remap(self.levels[level], col, row, cv2.INTER_LINEAR, borderMode=border, borderValue=0.0)


def _mask(n: np.ndarray, e: np.ndarray, periods: tuple[float, float, float]) -> np.ndarray:
    """A smooth 0..1 field with no visible period: three waves in different directions."""
    a, b, c = periods
    wave = np.sin(n / a + 0.3) * np.sin(e / b + 1.7) + 0.5 * np.sin((n + 0.6 * e) / c + 0.9)
    return np.clip(0.5 + 0.45 * wave, 0.0, 1.0).astype(np.float32)


@dataclass
class BookAppearance:
    """A fine-grained table top, a printed page on the book, a brick floor beyond the table."""

    book_half_size: tuple[float, float]
    book_yaw_rad: float
    book_thickness: float

    def __post_init__(self) -> None:
        self.table = (TextureLayer("gravel", 0.0012), TextureLayer("grass", 0.0019, 0.65, (100.0, 37.0)))
        h, w = photo("page").shape
        along, across = self.book_half_size
        texel = 2.0 * along / w  # the page fills the cover, its lines along the book's long side
        self.page = TextureLayer("page", texel, self.book_yaw_rad, (0.5 * w, 0.5 * h), False, (2.0 * across / h) / texel)
        self.floor = TextureLayer("brick", 0.004, 0.2)

    def radiance(self, n: np.ndarray, e: np.ndarray, down: np.ndarray, footprint_m: float) -> np.ndarray:
        mix = _mask(n, e, (0.05, 0.07, 0.11))
        table = mix * self.table[0].sample(n, e, footprint_m) + (1.0 - mix) * self.table[1].sample(n, e, footprint_m)
        value = 0.55 + 0.16 * table
        floor = 0.3 + 0.1 * self.floor.sample(n, e, footprint_m)
        value = np.where(down > 0.3, floor, value)
        on_book = down < -0.5 * self.book_thickness
        if np.any(on_book):
            value = np.where(on_book, 0.75 + 0.12 * self.page.sample(n, e, footprint_m), value)
        return value.astype(np.float32)


@dataclass
class LandfillAppearance:
    """Gravel and grass over rolling ground, shaded by the slope under a low sun."""

    ground_height: object  # the scenario's ground_height(n, e)
    sun_down: tuple[float, float, float] = (0.45, 0.3, 0.84)  # direction the sunlight travels (NED, unit)

    def __post_init__(self) -> None:
        self.coarse = (TextureLayer("gravel", 0.05), TextureLayer("grass", 0.11, 0.4, (200.0, 91.0)))
        self.fine = TextureLayer("gravel", 0.008, 1.1, (37.0, 300.0))

    def _shade(self, n: np.ndarray, e: np.ndarray) -> np.ndarray:
        """Lambert shading of the terrain: its upward normal (dn, de, -1)/|.| against the sunlight."""
        h = 0.5
        dn = (self.ground_height(n + h, e) - self.ground_height(n - h, e)) / (2 * h)
        de = (self.ground_height(n, e + h) - self.ground_height(n, e - h)) / (2 * h)
        sx, sy, sz = self.sun_down
        return ((sz - dn * sx - de * sy) / np.sqrt(1.0 + dn * dn + de * de)).astype(np.float32)

    def radiance(self, n: np.ndarray, e: np.ndarray, down: np.ndarray, footprint_m: float) -> np.ndarray:
        import cv2

        mix = _mask(n, e, (13.0, 17.0, 29.0))
        coarse = mix * self.coarse[0].sample(n, e, footprint_m) + (1.0 - mix) * self.coarse[1].sample(n, e, footprint_m)
        fine = self.fine.sample(n, e, footprint_m)
        shade = cv2.resize(self._shade(n[::8, ::8], e[::8, ::8]), (n.shape[1], n.shape[0]), interpolation=cv2.INTER_LINEAR)
        value = (0.5 + 0.14 * coarse + 0.06 * fine) * (0.55 + 0.45 * shade)
        return value.astype(np.float32)


def appearance_for(scenario: object) -> Appearance:
    """The look of a scenario's ground: its own ``appearance()`` if it has one, else by its name."""
    own = getattr(scenario, "appearance", None)
    if callable(own):
        return own()
    name = getattr(scenario, "name", "")
    if name == "book":
        return BookAppearance(scenario.book_half_size, scenario.book_yaw_rad, scenario.book_thickness)
    if name == "landfill":
        return LandfillAppearance(scenario.ground_height)
    raise ValueError(f"no ground appearance for scenario {name!r}")
