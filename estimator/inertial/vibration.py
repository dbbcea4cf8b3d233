"""The IMU's vibration floor from its own samples: the noise density in a band above the vehicle's motion.

A rotor shakes the IMU at tens of hertz while the vehicle's own motion lies below a few hertz, so the
spectral density of the readings between, say, 10 and 60 Hz is the vibration's, whatever the vehicle
does. It is the figure to hold against a noise model's white density (``ImuNoise``): a white model at
that density claims the same level down to 0 Hz, where the velocity error between two fixes is made.
Welch's method: the samples cut into half-overlapping Hann-windowed segments, their periodograms averaged.
"""

from __future__ import annotations

import numpy as np

DEFAULT_BAND_HZ = (10.0, 60.0)
SEGMENT = 1024  # samples per periodogram (5 s at 200 Hz: 0.2-Hz bins)


def spectral_density(samples: np.ndarray, rate_hz: float, segment: int = SEGMENT) -> tuple[np.ndarray, np.ndarray]:
    """One-sided power spectral density of each column of ``samples`` (n × k) [unit²/Hz] and its frequencies."""
    x = np.asarray(samples, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    if len(x) < segment:
        raise ValueError(f"vibration: {len(x)} samples, fewer than one segment of {segment}")
    if not (rate_hz > 0.0 and np.isfinite(rate_hz)):
        raise ValueError(f"vibration: sample rate must be positive, got {rate_hz}")
    window = np.hanning(segment)
    step = segment // 2
    starts = range(0, len(x) - segment + 1, step)
    total = np.zeros((segment // 2 + 1, x.shape[1]))
    for s in starts:
        piece = x[s:s + segment]
        piece = (piece - piece.mean(axis=0)) * window[:, None]
        total += np.abs(np.fft.rfft(piece, axis=0)) ** 2
    density = total / (len(starts) * rate_hz * np.sum(window**2))
    density[1:-1] *= 2.0  # one-sided: the negative frequencies folded in (not DC, not Nyquist)
    return np.fft.rfftfreq(segment, 1.0 / rate_hz), density


def vibration_floor(samples: np.ndarray, rate_hz: float, band_hz: tuple[float, float] = DEFAULT_BAND_HZ,
                    segment: int = SEGMENT) -> np.ndarray:
    """Per axis, the noise density [unit/√Hz] in ``band_hz``: the square root of the mean spectral density there."""
    lo, hi = band_hz
    if not 0.0 <= lo < hi <= rate_hz / 2.0:
        raise ValueError(f"vibration: band {lo:g}-{hi:g} Hz must lie within 0 and the Nyquist frequency {rate_hz / 2:g} Hz")
    freq, density = spectral_density(samples, rate_hz, segment)
    inside = (freq >= lo) & (freq < hi)
    if not np.any(inside):
        raise ValueError(f"vibration: no frequency bin in {lo:g}-{hi:g} Hz at {segment} samples per segment")
    return np.sqrt(density[inside].mean(axis=0))
