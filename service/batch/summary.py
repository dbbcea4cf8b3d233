"""The batch's one-page HTML summary: what a survey lead looks at first, in one self-contained file.

The counts, then four figures (the flights' smoothed tracks seen from above, their output quality
over time, position error filtered against smoothed where a truth exists, volume and its error
where a flight has LIDAR), the fleet table, and the failed flights with their errors. Figures are
PNGs embedded in the page (matplotlib, the ``plot`` extra); without it the page says so.
"""

from __future__ import annotations

import base64
import html
import io
import os
from pathlib import Path
from typing import Any

import numpy as np

from vtolpose.drivers.files.tum import read_tum

TRACK_POINTS = 2000  # per flight in the tracks figure
TABLE_COLUMNS = (("flight", "flight"), ("status", "status"), ("duration_s", "duration s"), ("distance_m", "distance m"),
                 ("resets", "resets"), ("quality_mean", "quality"), ("quality_usable_fraction", "usable"),
                 ("gps_rejected", "GPS rejected"), ("position_rmse_m", "RMSE m"),
                 ("smoothed_position_rmse_m", "smoothed RMSE m"), ("volume_m3", "volume m³"),
                 ("volume_error_percent", "volume error %"), ("pose_height_error_cells_m", "height error over cells m"),
                 ("wall_s", "wall s"))


def _png(fig, plt) -> str:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    plt.close(fig)
    return f'<img src="data:image/png;base64,{base64.b64encode(buffer.getvalue()).decode()}">'


def _track(folder: Path) -> np.ndarray | None:
    try:
        _, p, _ = read_tum(folder / "trajectory-smoothed.txt")
    except (OSError, ValueError):
        return None
    step = max(1, len(p) // TRACK_POINTS)
    return p[::step] if len(p) else None


def figures(rows: list[dict[str, Any]], out_root: Path) -> list[str]:
    """The page's figures as ``<img>`` tags (empty without matplotlib or without a finished flight)."""
    from vtolpose.service.calibration.plots import _pyplot

    plt = _pyplot()
    ok = [r for r in rows if r["status"] in ("done", "skipped")]
    if not ok:
        return []
    out = []
    fig, ax = plt.subplots(figsize=(6, 5.5))
    for row in ok:
        track = _track(out_root / row["flight"])
        if track is not None:
            ax.plot(track[:, 1], track[:, 0], lw=1, label=row["flight"])
    ax.set(xlabel="east [m]", ylabel="north [m]", title="smoothed tracks (each flight in its own frame)")
    ax.set_aspect("equal", adjustable="datalim")
    if len(ok) <= 12:
        ax.legend(fontsize=7)
    out.append(_png(fig, plt))
    fig, ax = plt.subplots(figsize=(6, 4))
    for row in ok:
        values = row.get("quality_over_time") or []
        if values:
            x = (np.arange(len(values)) + 0.5) * float(row.get("quality_bin_s") or 10.0) / 60.0
            ax.plot(x, [np.nan if v is None else v for v in values], marker=".", lw=1, label=row["flight"])
    ax.set(xlabel="time into the flight [min]", ylabel="mean output quality (0-100)", ylim=(0, 101),
           title="output quality over time")
    out.append(_png(fig, plt))
    scored = [r for r in ok if r.get("position_rmse_m") is not None]
    if scored:
        fig, ax = plt.subplots(figsize=(6, 4))
        x = np.arange(len(scored))
        ax.bar(x - 0.2, [r["position_rmse_m"] for r in scored], 0.4, label="filtered")
        ax.bar(x + 0.2, [r.get("smoothed_position_rmse_m") or np.nan for r in scored], 0.4, label="smoothed")
        ax.set_xticks(x, [r["flight"] for r in scored], rotation=60, ha="right", fontsize=7)
        ax.set(ylabel="position RMSE [m]", title="position error against truth")
        ax.legend()
        fig.tight_layout()
        out.append(_png(fig, plt))
    mapped = [r for r in ok if r.get("volume_m3") is not None]
    if mapped:
        fig, ax = plt.subplots(figsize=(6, 4))
        x = np.arange(len(mapped))
        ax.bar(x, [r["volume_m3"] for r in mapped], 0.6, label="volume (smoothed poses)")
        ax.set_xticks(x, [r["flight"] for r in mapped], rotation=60, ha="right", fontsize=7)
        ax.set(ylabel="volume above the base [m³]", title="mapped volume, error where the ground is known")
        for k, r in enumerate(mapped):
            if r.get("volume_error_percent") is not None:
                ax.annotate(f"{r['volume_error_percent']:+.2f} %", (k, r["volume_m3"]), ha="center", va="bottom", fontsize=7)
        fig.tight_layout()
        out.append(_png(fig, plt))
    return out


def _fmt(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.4g}"
    return html.escape(str(value))


def write_summary(rows: list[dict[str, Any]], out_root: Path, where: str, wall_s: float, plots: bool = True) -> Path:
    """``fleet.html`` in ``out_root`` (written under a temporary name, then renamed)."""
    counts = {s: sum(r["status"] == s for r in rows) for s in ("done", "skipped", "failed")}
    images = figures(rows, out_root) if plots else []
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>vtolpose batch</title><style>"
        "body{font-family:sans-serif;margin:1.5em}table{border-collapse:collapse;font-size:0.85em}"
        "td,th{border:1px solid #bbb;padding:2px 6px;text-align:right}td:first-child,th:first-child{text-align:left}"
        ".failed{background:#fdd}img{margin:4px}</style></head><body>",
        f"<h1>vtolpose batch: {len(rows)} flights</h1>",
        f"<p>{counts['done']} run, {counts['skipped']} unchanged since their last run (not run again), "
        f"{counts['failed']} failed; {wall_s:.1f} s on {html.escape(where)}. Table: fleet.parquet, fleet.csv; each "
        "flight's trajectories, report and map in its own folder.</p>",
    ]
    if images:
        parts.append("<div>" + "".join(images) + "</div>")
    elif plots:
        parts.append("<p>(no figures: no flight finished)</p>")
    else:
        parts.append("<p>(no figures: drawing them needs matplotlib, the <code>plot</code> extra)</p>")
    head = "".join(f"<th>{html.escape(label)}</th>" for _, label in TABLE_COLUMNS)
    body = "".join(f"<tr class='{'failed' if r['status'] == 'failed' else ''}'>"
                   + "".join(f"<td>{_fmt(r.get(key))}</td>" for key, _ in TABLE_COLUMNS) + "</tr>" for r in rows)
    parts.append(f"<h2>Flights</h2><table><tr>{head}</tr>{body}</table>")
    failed = [r for r in rows if r["status"] == "failed"]
    if failed:
        parts.append("<h2>Failed</h2><ul>" + "".join(
            f"<li><b>{html.escape(r['flight'])}</b> ({html.escape(r['input'])}): {html.escape(str(r.get('error')))}</li>"
            for r in failed) + "</ul>")
    parts.append("</body></html>\n")
    path = out_root / "fleet.html"
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text("".join(parts), encoding="utf-8")
    os.replace(tmp, path)
    return path
