"""PNG figures of the calibrations: what a field team looks at before trusting a number.

matplotlib is an optional extra (``pip install matplotlib``, or ``pip install -e '.[plot]'`` from a checkout); it is imported only when a
figure is drawn, with a message saying how to get it (or to pass ``--no-plot``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from vtolpose.estimator import ChessboardCalibration, FLAT_FACTOR, ImuCalibrationResult, LatencyScan, TimeSyncResult


class PlotUnavailable(ValueError):
    """matplotlib is missing."""


def _pyplot() -> Any:
    try:
        import matplotlib
    except ImportError:
        raise PlotUnavailable(
            "drawing the figure needs matplotlib: pip install matplotlib (from a checkout: pip install -e '.[plot]'), or pass --no-plot") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt: Any, fig: Any, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_allan(path: str | Path, result: ImuCalibrationResult) -> Path:
    """Allan deviation of each axis with the fitted white-noise, bias-instability and random-walk lines."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    tau = result.curve.tau
    colours = ("tab:red", "tab:green", "tab:blue")
    for ax, sensor, fits, offset, unit in ((axes[0], "gyro", result.gyro_fits, 0, "rad/s"),
                                           (axes[1], "accel", result.accel_fits, 3, "m/s²")):
        for k, (fit, colour) in enumerate(zip(fits, colours)):
            axis = "xyz"[k]
            ax.loglog(tau, result.curve.adev[:, offset + k], "o", ms=3, color=colour, label=f"{axis}: measured")
            ax.loglog(tau, fit.white_noise / np.sqrt(tau), "--", lw=1, color=colour,
                      label=f"{axis}: N = {fit.white_noise:.2e} /√Hz")
            flat = FLAT_FACTOR * fit.bias_instability
            ax.loglog([fit.bias_instability_tau / 3, fit.bias_instability_tau * 3], [flat, flat], "-", lw=2, color=colour,
                      alpha=0.5, label=f"{axis}: B {'≤' if fit.bias_instability_is_bound else '='} {fit.bias_instability:.2e}")
            if fit.random_walk is not None:
                ax.loglog(tau, fit.random_walk * np.sqrt(tau / 3.0), ":", lw=1.5, color=colour,
                          label=f"{axis}: K = {fit.random_walk:.2e} ·√Hz")
        ax.set_title(f"{sensor}: Allan deviation, {result.stretch.duration_s:.0f} s at rest")
        ax.set_xlabel("cluster time τ [s]")
        ax.set_ylabel(f"σ(τ) [{unit}]")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, ncol=1)
    fig.tight_layout()
    return _save(plt, fig, path)


def plot_reprojection(path: str | Path, cal: ChessboardCalibration) -> Path:
    """Per-view RMS reprojection error (views to drop in red) and every corner's residual vector."""
    plt = _pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 5), gridspec_kw={"width_ratios": [3, 2]})
    x = np.arange(len(cal.view_names))
    colours = ["tab:red" if n in cal.drop else "tab:blue" for n in cal.view_names]
    left.bar(x, cal.view_rms_px, color=colours)
    left.axhline(cal.rms_px, color="k", ls="--", lw=1, label=f"overall RMS {cal.rms_px:.3f} px")
    left.set_xticks(x, cal.view_names, rotation=70, fontsize=7)
    left.set_ylabel("RMS reprojection error [px]")
    left.set_title(f"{len(cal.view_names)} views" + (f"; red: drop ({len(cal.drop)})" if cal.drop else ""))
    left.legend()
    for r, colour in zip(cal.residuals, colours):
        right.plot(r[:, 0], r[:, 1], ".", ms=3, color=colour, alpha=0.6)
    right.set_aspect("equal")
    right.axhline(0, color="k", lw=0.5)
    right.axvline(0, color="k", lw=0.5)
    right.set_xlabel("residual u [px]")
    right.set_ylabel("residual v [px]")
    right.set_title("corner residuals (measured − reprojected)")
    fig.tight_layout()
    return _save(plt, fig, path)


def plot_latency(path: str | Path, scan: LatencyScan, what: str = "GPS") -> Path:
    """Total and per-window normalised residual against the time offset, the best offset ± σ."""
    plt = _pyplot()
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 7), sharex=True)
    ms = scan.offsets_s * 1e3
    top.plot(ms, scan.cost, "k.-", label="all windows")
    top.axvline(scan.offset_s * 1e3, color="tab:red", label=f"offset {scan.offset_s * 1e3:+.1f} ± {scan.sigma_s * 1e3:.1f} ms")
    top.axvspan((scan.offset_s - scan.sigma_s) * 1e3, (scan.offset_s + scan.sigma_s) * 1e3, color="tab:red", alpha=0.2)
    top.set_ylabel("Σ normalised residual²")
    top.set_title(f"{what} time offset (added to the stamps): in-motion alignment residual, "
                  f"{len(scan.windows)} windows, {scan.n_fixes} fixes")
    top.legend()
    for k in range(scan.window_cost.shape[1]):
        c = scan.window_cost[:, k]
        bottom.plot(ms, c / c.min(), lw=1, label=f"window {k + 1}: {scan.window_offsets_s[k] * 1e3:+.0f} ms")
    bottom.set_xlabel("time offset [ms]")
    bottom.set_ylabel("residual / its minimum")
    bottom.legend(fontsize=7, ncol=2)
    for ax in (top, bottom):
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return _save(plt, fig, path)


def plot_correlation(path: str | Path, result: TimeSyncResult) -> Path:
    """Gyro–camera correlation against the offset (whole scan and around the peak), and the two
    rotation rates side by side at the offset found."""
    plt = _pyplot()
    fig = plt.figure(figsize=(12, 8))
    whole, zoom, rates = fig.add_subplot(2, 2, 1), fig.add_subplot(2, 2, 2), fig.add_subplot(2, 1, 2)
    ms = result.lags_s * 1e3
    label = f"offset {result.offset_s * 1e3:+.1f} ± {result.sigma_s * 1e3:.1f} ms"
    for ax in (whole, zoom):
        ax.plot(ms, result.correlation, "k-", lw=1)
        ax.axvline(result.offset_s * 1e3, color="tab:red", label=label)
        ax.axvspan((result.offset_s - result.sigma_s) * 1e3, (result.offset_s + result.sigma_s) * 1e3,
                   color="tab:red", alpha=0.25)
        ax.set_xlabel("offset added to camera stamps [ms]")
        ax.grid(True, alpha=0.3)
    whole.set_ylabel("correlation")
    whole.set_title(f"gyro vs camera rotation, {result.n_pairs} frame pairs (peak {result.peak:.3f})")
    whole.legend()
    half = max(20.0 * result.sigma_s, 0.01) * 1e3
    near = np.abs(ms - result.offset_s * 1e3) <= half
    zoom.set_xlim(result.offset_s * 1e3 - half, result.offset_s * 1e3 + half)
    zoom.set_ylim(result.correlation[near].min(), result.peak + 0.1 * (result.peak - result.correlation[near].min()) + 1e-9)
    zoom.set_title("around the peak: its sharpness")
    for i, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
        rates.plot(result.t_mid_s, result.camera_rate[:, i], ".", ms=3, color=colour, label=f"camera {'xyz'[i]}")
        rates.plot(result.t_mid_s, result.gyro_rate[:, i], "-", lw=0.8, color=colour, label=f"gyro {'xyz'[i]}")
    rates.set_xlabel("time [s]")
    rates.set_ylabel("rotation rate, camera axes [rad/s]")
    rates.set_title("at the offset found")
    rates.legend(fontsize=7, ncol=6)
    rates.grid(True, alpha=0.3)
    fig.tight_layout()
    return _save(plt, fig, path)
