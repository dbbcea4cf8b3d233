"""Calibration results as configuration blocks: YAML that ``config.load_config`` accepts as is.

Every block is checked against the schema before it is written, so a block that the
configuration would refuse is a bug here, never a surprise in the field. Numbers are rounded to
six significant digits: more than any of these calibrations can support.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any, Callable

import numpy as np
import yaml

from vtolpose.config import validate
from vtolpose.estimator import ChessboardCalibration, ImuCalibrationResult
from vtolpose.service.calibration.options import add_output_options  # noqa: F401 - where the jobs found it


def _num(x: float) -> float:
    return float(f"{float(x):.6g}")


def _vec(v: np.ndarray | None) -> list[float] | None:
    return None if v is None else [_num(x) for x in np.asarray(v, dtype=float).reshape(-1)]


def imu_tree(result: ImuCalibrationResult) -> dict[str, Any]:
    """``estimator.imu.noise`` (the largest axis of each figure: the filter takes one number) and
    ``calibration.imu`` (every figure per axis)."""
    fig = result.figure

    def worst(values: np.ndarray | None) -> float | None:
        return None if values is None else _num(np.max(values))

    return {
        "estimator": {"imu": {"noise": {
            "gyro_noise_density": worst(fig("gyro", "white_noise")),
            "gyro_random_walk": worst(fig("gyro", "random_walk")),
            "accel_noise_density": worst(fig("accel", "white_noise")),
            "accel_random_walk": worst(fig("accel", "random_walk")),
        }}},
        "calibration": {"imu": {
            "gravity": _num(result.gravity),
            "gyro_bias": _vec(result.gyro_bias),
            "roll_deg": _num(math.degrees(result.roll_rad)),
            "pitch_deg": _num(math.degrees(result.pitch_rad)),
            "gyro_noise_density": _vec(fig("gyro", "white_noise")),
            "gyro_bias_instability": _vec(fig("gyro", "bias_instability")),
            "gyro_random_walk": _vec(fig("gyro", "random_walk")),
            "accel_noise_density": _vec(fig("accel", "white_noise")),
            "accel_bias_instability": _vec(fig("accel", "bias_instability")),
            "accel_random_walk": _vec(fig("accel", "random_walk")),
        }},
    }


def camera_tree(cal: ChessboardCalibration, time_offset_s: float | None = None) -> dict[str, Any]:
    k1, k2, p1, p2, k3 = (_num(x) for x in cal.distortion)
    K = cal.K
    block = {"width": cal.width, "height": cal.height, "fx": _num(K[0, 0]), "fy": _num(K[1, 1]),
             "cx": _num(K[0, 2]), "cy": _num(K[1, 2]), "k1": k1, "k2": k2, "p1": p1, "p2": p2, "k3": k3,
             "rms_reprojection_px": _num(cal.rms_px)}
    if time_offset_s is not None:
        block["time_offset_s"] = _num(time_offset_s)
    return {"calibration": {"camera": block}}


def camera_offset_tree(time_offset_s: float) -> dict[str, Any]:
    return {"calibration": {"camera": {"time_offset_s": _num(time_offset_s)}}}


def gps_tree(time_offset_s: float | None = None, lever_arm_b: np.ndarray | None = None) -> dict[str, Any]:
    block: dict[str, Any] = {}
    if time_offset_s is not None:
        block["time_offset_s"] = _num(time_offset_s)
    if lever_arm_b is not None:
        block["lever_arm_b"] = _vec(lever_arm_b)
    return {"calibration": {"gps": block}}


def dataset_camera_block(cal: ChessboardCalibration) -> str:
    """The same intrinsics as a ``camera:`` block of ``dataset.yaml`` (one line, for a comment)."""
    K = cal.K
    doc = {"width": cal.width, "height": cal.height, "fx": _num(K[0, 0]), "fy": _num(K[1, 1]),
           "cx": _num(K[0, 2]), "cy": _num(K[1, 2]), "distortion": _vec(cal.distortion)}
    return "camera: " + yaml.safe_dump(doc, default_flow_style=True, sort_keys=False, width=1000).strip()


class _BlockDumper(yaml.SafeDumper):
    """Mappings as blocks (one key a line, as in default.yaml), vectors on one line."""


_BlockDumper.add_representer(list, lambda d, v: d.represent_sequence("tag:yaml.org,2002:seq", v, flow_style=True))


def config_block(tree: dict[str, Any], header: list[str]) -> str:
    """YAML text of ``tree`` under ``# header`` comment lines; refuses a tree the schema refuses."""
    validate(tree, "calibration block")
    comments = "".join(f"# {line}\n" if line else "#\n" for line in header)
    body = yaml.dump(tree, Dumper=_BlockDumper, sort_keys=False, default_flow_style=False, width=120, allow_unicode=True)
    return comments + body


def write_block(path: str | Path, text: str) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8", newline="\n")
    return path


def plot_path(args: argparse.Namespace) -> Path | None:
    if getattr(args, "no_plot", True):
        return None
    return Path(args.plot) if args.plot else Path(args.out).with_suffix(".png")


def finish(args: argparse.Namespace, text: str, summary: list[str], draw: Callable[[Path], Any]) -> int:
    """Draw the figure, then write the block (so a missing matplotlib leaves no half result), and
    print the summary and where they went."""
    figure = plot_path(args)
    if figure is not None:
        draw(figure)
    path = write_block(args.out, text)
    print("\n".join(summary))
    print(f"wrote {path}" + (f" and {figure}" if figure is not None else ""))
    return 0
