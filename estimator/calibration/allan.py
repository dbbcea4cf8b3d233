"""Overlapping Allan deviation of a static IMU record, and the noise figures it shows.

For a rate signal sampled at ``rate_hz`` the Allan variance at cluster time τ is half the mean
square difference of consecutive τ-averages. Each classic noise leaves its own slope on a log-log
plot of the deviation σ(τ) (IEEE Std 952):

    white noise            σ² = N² / τ          (slope −½; N is the density, e.g. rad/s/√Hz)
    bias instability       σ ≈ 0.664 B           (flat; B is read at the curve's minimum)
    bias random walk       σ² = K² τ / 3        (slope +½; K is the random-walk density)

N and K are fitted together with a flat term to the variance (non-negative least squares,
weighted by how many independent clusters each τ has), so that their overlap near the curve's
minimum does not bias either. K counts as measured only when the curve turns upward well
inside the record; otherwise it is reported as unmeasured, never as a small number.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

FLAT_FACTOR = math.sqrt(2.0 * math.log(2.0) / math.pi)  # σ of bias instability ≈ 0.664 B
MIN_CLUSTERS = 10  # a τ with fewer independent clusters than this is too uncertain to rely on


@dataclass(frozen=True, slots=True)
class AllanCurve:
    """σ(τ) per channel: ``tau`` (M,), ``adev`` (M, C), ``clusters`` (M,) independent clusters per τ."""

    tau: np.ndarray
    adev: np.ndarray
    clusters: np.ndarray
    duration_s: float


@dataclass(frozen=True, slots=True)
class AllanFit:
    """Noise figures of one channel; ``None`` where the record cannot show them."""

    white_noise: float  # N: density [unit·√s], e.g. rad/s/√Hz
    bias_instability: float  # B = min σ / 0.664 [unit]
    bias_instability_tau: float  # τ of that minimum [s]
    bias_instability_is_bound: bool  # the curve still falls at the longest reliable τ: B is an upper bound
    random_walk: float | None  # K: density [unit/√s], e.g. rad/s²/√Hz
    random_walk_bound: float  # K is at most this (from the longest reliable τ) when unmeasured
    flat: float  # fitted flat term of σ [unit]

    def model(self, tau: np.ndarray) -> np.ndarray:
        """σ(τ) of the fitted model (for plots)."""
        k = self.random_walk or 0.0
        return np.sqrt(self.white_noise**2 / tau + self.flat**2 + k**2 * tau / 3.0)


def cluster_sizes(n: int, points_per_decade: int = 10, max_fraction: float = 0.25) -> np.ndarray:
    """Log-spaced cluster sizes ``m`` from 1 to ``max_fraction`` of the record, without repeats."""
    top = max(1, int(n * max_fraction))
    m = np.unique(np.round(np.logspace(0.0, math.log10(top), max(2, int(points_per_decade * math.log10(top)) + 1))))
    return m.astype(np.int64)


def allan_deviation(samples: np.ndarray, rate_hz: float, points_per_decade: int = 10) -> AllanCurve:
    """Overlapping Allan deviation of evenly sampled ``samples`` (N,) or (N, C)."""
    x = np.asarray(samples, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    n = len(x)
    if n < 16:
        raise ValueError(f"Allan deviation needs at least 16 samples, got {n}")
    tau0 = 1.0 / rate_hz
    # Integral of the rate (angle / velocity) at the sample boundaries; the mean is removed first
    # so that the running sum of a large mean (gravity) does not swamp the differences.
    theta = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x - x.mean(axis=0), axis=0) * tau0])
    sizes = cluster_sizes(n, points_per_decade)
    adev = np.empty((len(sizes), x.shape[1]))
    for i, m in enumerate(sizes):
        d = theta[2 * m:] - 2.0 * theta[m:-m] + theta[: n + 1 - 2 * m]
        tau = m * tau0
        adev[i] = np.sqrt(np.mean(d * d, axis=0) / (2.0 * tau * tau))
    return AllanCurve(sizes * tau0, adev, n / sizes.astype(float), n * tau0)


def fit_noise(curve: AllanCurve, channel: int = 0, min_tau: float = 0.0) -> AllanFit:
    """White noise, bias instability and random walk of one channel of ``curve``."""
    tau, sigma = curve.tau, curve.adev[:, channel]
    reliable = curve.clusters >= MIN_CLUSTERS
    use = reliable & (tau >= min_tau)
    if np.count_nonzero(use) < 4:
        raise ValueError(f"the record ({curve.duration_s:.1f} s) is too short for an Allan fit: record longer")
    t, v = tau[use], sigma[use] ** 2
    A = np.column_stack([1.0 / t, np.ones_like(t), t / 3.0])
    # Relative scatter of an Allan variance estimate ≈ √(2 / (clusters − 1)); weight by the
    # model's own variance (two passes) rather than the noisy measured one, which biases low.
    rel = np.sqrt(2.0 / np.maximum(curve.clusters[use] - 1.0, 1.0))
    pred = v
    for _ in range(3):
        w = 1.0 / (np.maximum(pred, 1e-300) * rel)
        coef, _ = nnls(A * w[:, None], v * w)
        pred = A @ coef
    a, b, c = coef
    if a <= 0.0:
        raise ValueError("no white noise in the Allan curve (does the record hold constant or repeated values?)")
    t_last = t[-1]
    # The random walk is believed when it dominates the curve at the longest reliable τ, i.e. the
    # curve has turned upward inside the record.
    rises = c > 0.0 and c * t_last / 3.0 > a / t_last + b
    rel_sigma = sigma[reliable]
    i_min = int(np.argmin(rel_sigma))
    last_reliable = np.flatnonzero(reliable)[-1]
    return AllanFit(
        white_noise=math.sqrt(a),
        bias_instability=float(rel_sigma[i_min] / FLAT_FACTOR),
        bias_instability_tau=float(tau[reliable][i_min]),
        bias_instability_is_bound=i_min == len(rel_sigma) - 1,
        random_walk=math.sqrt(c) if rises else None,
        random_walk_bound=float(sigma[last_reliable] * math.sqrt(3.0 / tau[last_reliable])),
        flat=math.sqrt(b),
    )
