"""``vtolpose bench --only camera-mounting``: the camera's mounting estimated online, on two cells of the camera matrix.

The base cell (gentle) and the aggressive one (fast turns) are rendered once each, as for ``camera-clock``
(:func:`~vtolpose.service.bench.camera_clock.render`). Test 2 (IMU+camera) and Test 3 (IMU+camera+GPS) replay
each with the mounting given right (the rendered ``R_BC``) and 1° wrong: the ``R_BC`` in a copy of the dataset's
``dataset.yaml`` turned by 1° about body x (not the optical axis, which is body z), ``R_BC_given = Exp(ε) R_BC``.
The filter's correction is ``R_BC = Exp(φ) R_BC_given``: the one to find is ``φ = −ε``, −1° about body x, no
translation. Each with the mounting estimation (``estimator.camera.estimate_extrinsics``) off and on, and once with
the time offset 10 ms wrong as well, both estimated or neither.
"""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.estimator import so3_exp
from vtolpose.service.bench.camera_clock import CELLS, TESTS, WRONG_OFFSET_S, render
from vtolpose.service.bench.camera_matrix import TestScore
from vtolpose.service.bench.rows import Row
from vtolpose.service.replay.report import build_report
from vtolpose.service.replay.session import replay
from vtolpose.service.runtime.kernels import load_compiled_kernels

WRONG_MOUNTING = np.radians([1.0, 0.0, 0.0])  # ε: the turn, about body x, of the R_BC given to the replay
CASES = (  # name, mounting given 1° wrong, its estimation on, configured time offset [s], its estimation on
    ("right, off", False, False, 0.0, False),
    ("right, on", False, True, 0.0, False),
    ("1° wrong, off", True, False, 0.0, False),
    ("1° wrong, on", True, True, 0.0, False),
    ("1° and 10 ms wrong, both off", True, False, WRONG_OFFSET_S, False),
    ("1° and 10 ms wrong, both on", True, True, WRONG_OFFSET_S, True),
)


def mounted_wrong(dataset: Dataset, work: Path, rotvec: np.ndarray) -> Dataset:
    """``dataset`` with its camera's ``R_BC`` turned to ``Exp(rotvec) R_BC`` (in ``work``: a new ``dataset.yaml``
    beside links to everything else)."""
    work.mkdir(parents=True, exist_ok=True)
    for entry in dataset.root.iterdir():
        if entry.name != "dataset.yaml":
            (work / entry.name).symlink_to(entry.resolve())
    document = yaml.safe_load((dataset.root / "dataset.yaml").read_text())
    R_BC = np.asarray(document["camera"]["R_BC"], dtype=float)
    document["camera"]["R_BC"] = (so3_exp(np.asarray(rotvec, dtype=float)) @ R_BC).tolist()
    (work / "dataset.yaml").write_text(yaml.safe_dump(document, sort_keys=False))
    return Dataset.open(work)


def replay_case(dataset: Dataset, sensors: list[str], estimate: bool, offset_s: float, estimate_offset: bool
                ) -> tuple[TestScore, dict | None]:
    """One replay: the score and the estimated mounting correction (the report's ``camera.extrinsics``)."""
    cfg = load_config(None, {"calibration": {"camera": {"time_offset_s": offset_s}},
                             "estimator": {"camera": {"estimate_extrinsics": estimate, "estimate_time_offset": estimate_offset}}})
    report = build_report(replay(dataset, cfg, sensors), dataset, cfg)
    return TestScore.of(report), (report.get("camera") or {}).get("extrinsics")


def correction_text(mounting: dict | None) -> str:
    """The rotation correction (deg) and translation correction (mm) per body axis, each ± its sigma."""
    if mounting is None:
        return "—"
    rot, tr = mounting["rotation_deg"], mounting["translation_mm"]
    turn = ", ".join(f"{e:+.2f}±{s:.2f}" for e, s in zip(rot["estimate"], rot["sigma"]))
    shift = ", ".join(f"{e:+.0f}±{s:.0f}" for e, s in zip(tr["estimate"], tr["sigma"]))
    return f"φ {turn}°; c {shift} mm"


def sigmas_off(mounting: dict, truth_deg: np.ndarray) -> np.ndarray:
    """How many sigmas the rotation correction is from the truth, per body axis."""
    rot = mounting["rotation_deg"]
    return np.abs(np.asarray(rot["estimate"]) - truth_deg) / np.maximum(rot["sigma"], 1e-9)


def bench_camera_mounting(echo: Callable[[str], None] = print) -> list[Row]:
    """Base and aggressive cells, Tests 2 and 3: the camera mounting right and 1° wrong (and 10 ms wrong too), its estimation off and on."""
    rows = []
    lines = ["| cell | case | test | position, attitude, NEES mean / in band, resets | correction found (truth φ_x −1.00° when wrong) |",
             "|---|---|---|---|---|"]
    for cell in CELLS:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            right = render(cell, Path(tmp))
            wrong = mounted_wrong(right, Path(tmp) / "wrong", WRONG_MOUNTING)
            echo(f"  {cell.name}: rendered {cell.settings()} in {time.perf_counter() - t0:.0f} s")
            load_compiled_kernels()
            for case, is_wrong, estimate, offset_s, estimate_offset in CASES:
                truth_deg = -np.degrees(WRONG_MOUNTING) if is_wrong else np.zeros(3)
                for test, sensors in TESTS:
                    t0 = time.perf_counter()
                    score, mounting = replay_case(wrong if is_wrong else right, sensors, estimate, offset_s, estimate_offset)
                    found = correction_text(mounting)
                    echo(f"  {cell.name}, {case}, {test}: {score.text()}, {found} ({time.perf_counter() - t0:.0f} s)")
                    lines.append(f"| {cell.name} | {case} | {test} | {score.text()} | {found} |")
                    if mounting is not None:  # about x, the axis of the error; the worst axis (z trades with the yaw)
                        off = sigmas_off(mounting, truth_deg)
                        rows.append(Row(f"camera-mounting {cell.name} {case} {test}: |φ_x − true| / sigma", off[0], "x", "", "<= 2"))
                        rows.append(Row(f"camera-mounting {cell.name} {case} {test}: |φ − true| / sigma, worst axis", off.max(), "x"))
                    if score.attitude_deg is not None and math.isfinite(score.attitude_deg):
                        rows.append(Row(f"camera-mounting {cell.name} {case} {test}: attitude", score.attitude_deg, "deg"))
    for line in lines:
        echo("  " + line)
    return rows
