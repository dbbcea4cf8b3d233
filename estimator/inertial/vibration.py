"""The IMU's vibration floor from its own samples: the noise density in a band above the vehicle's motion.

A rotor shakes the IMU at tens of hertz while the vehicle's own motion lies below a few hertz, so the
spectral density of the readings between, say, 10 and 60 Hz is the vibration's, whatever the vehicle
does. It is the figure to hold against a noise model's white density (``ImuNoise``): a white model at
that density claims the same level down to 0 Hz, where the velocity error between two fixes is made.
Welch's method: the samples cut into half-overlapping Hann-windowed segments, their periodograms averaged.
"""

from __future__ import annotations

import numpy as np

from vtolpose.estimator.core.rotation import quat_to_rot
from vtolpose.estimator.metrics import interpolate_poses

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


LOW_BANDS_HZ = ((0.05, 0.3), (0.3, 1.0), (1.0, 3.0))  # where the velocity error between two fixes is made
LOW_PASS_HZ = 4.0  # both sides low-passed here alike: the bands kept, the rotor and the truth's noise gone


def specific_force_residual(imu_t_ns: np.ndarray, accel: np.ndarray, truth_t_ns: np.ndarray, p_w: np.ndarray,
                            q_wb: np.ndarray, R_bi: np.ndarray, gravity_w: np.ndarray,
                            low_pass_hz: float = LOW_PASS_HZ) -> tuple[np.ndarray, float]:
    """The accelerometer's error below a few hertz, where its own spectrum cannot tell error from motion: its
    readings turned into the world by the truth's attitude (``q_wb``, interpolated) and the mounting ``R_bi``,
    gravity added back, against the truth's track's acceleration (a quintic spline's), both low-passed alike
    (``low_pass_hz``, zero phase), the difference turned into the IMU's axes. Returns the residual on the
    truth's time grid (mean not removed: the bias) and the grid's rate.

    The truth's own errors (its attitude times g, its track's noise) count here too: the figure bounds the
    accelerometer's error from above.
    """
    from scipy.interpolate import make_interp_spline
    from scipy.signal import butter, sosfiltfilt

    truth_t_ns, imu_t_ns = np.asarray(truth_t_ns, np.int64), np.asarray(imu_t_ns, np.int64)
    truth_s, imu_s = (truth_t_ns - truth_t_ns[0]) * 1e-9, (imu_t_ns - truth_t_ns[0]) * 1e-9
    dt, imu_dt = float(np.median(np.diff(truth_s))), float(np.median(np.diff(imu_s)))
    if not 0.0 < low_pass_hz < 0.4 / dt or len(truth_s) < 64:
        raise ValueError(f"vibration: a truth every {dt * 1e3:.1f} ms ({len(truth_s)} samples) is too coarse or "
                         f"too short to resolve {low_pass_hz:g} Hz")
    inside = (imu_t_ns >= truth_t_ns[0]) & (imu_t_ns <= truth_t_ns[-1])
    imu_t_ns, imu_s, accel = imu_t_ns[inside], imu_s[inside], np.asarray(accel, float)[inside]
    R_imu = quat_to_rot(interpolate_poses(imu_t_ns, truth_t_ns, p_w, q_wb)[1])
    moving_w = np.einsum("nij,nj->ni", R_imu, accel @ R_bi.T) + gravity_w  # what the IMU says the vehicle did
    moving_w = sosfiltfilt(butter(4, low_pass_hz, fs=1.0 / imu_dt, output="sos"), moving_w, axis=0)
    grid = np.arange(truth_s[0] + dt, truth_s[-1] - dt, dt)
    track_w = make_interp_spline(truth_s, np.asarray(p_w, float), k=5, axis=0).derivative(2)(grid)  # a quintic: a
    # second difference (or a cubic's) would damp a 1-Hz swing by 1 % at 20 Hz, more than the error looked for
    track_w = sosfiltfilt(butter(4, low_pass_hz, fs=1.0 / dt, output="sos"), track_w, axis=0)
    said_w = np.stack([np.interp(grid, imu_s, moving_w[:, i]) for i in range(3)], axis=-1)
    grid_ns = truth_t_ns[0] + np.round(grid * 1e9).astype(np.int64)
    R_grid = quat_to_rot(interpolate_poses(grid_ns, truth_t_ns, p_w, q_wb)[1])
    return np.einsum("nji,nj->ni", R_grid, said_w - track_w) @ R_bi, 1.0 / dt


def band_densities(residual: np.ndarray, rate_hz: float, bands_hz: tuple[tuple[float, float], ...] = LOW_BANDS_HZ,
                   segment_s: float = 20.0) -> np.ndarray:
    """Per band (rows) and axis (columns), the residual's density [unit/√Hz] (Welch, ``segment_s`` segments)."""
    freq, density = spectral_density(residual, rate_hz, int(round(segment_s * rate_hz)))
    out = np.empty((len(bands_hz), density.shape[1]))
    for k, (lo, hi) in enumerate(bands_hz):
        inside = (freq >= lo) & (freq < hi)
        if not np.any(inside):
            raise ValueError(f"vibration: no frequency bin in {lo:g}-{hi:g} Hz with {segment_s:g}-s segments")
        out[k] = np.sqrt(density[inside].mean(axis=0))
    return out
