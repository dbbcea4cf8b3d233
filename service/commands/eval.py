"""``vtolpose eval``: score any TUM or EuRoC trajectory against truth."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.files.series import TruthSeries
from vtolpose.drivers.files.tum import read_tum
from vtolpose.estimator.metrics import evaluate
from vtolpose.service.commands.common import write_json


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "eval",
        help="score a trajectory against truth (RMSE, drift)",
        description="Score an estimated trajectory (TUM, or EuRoC CSV) against truth, in the shared NED frame\n"
        "(no alignment). TRUTH is a dataset folder (its truth and tracked point are used) or a TUM /\n"
        "EuRoC ground-truth / position CSV file.\n\n"
        "Example:\n  vtolpose eval traj.txt --truth data/book",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("trajectory", metavar="TRAJ", help="estimated trajectory (TUM or EuRoC)")
    p.add_argument("--truth", required=True, metavar="TRUTH", help="dataset folder or truth file")
    p.add_argument("--point-b", metavar="X,Y,Z", help="body point the truth tracks [m, FRD] (default: dataset's, or 0)")
    p.add_argument("--report", metavar="FILE.json", help="also write the scores as JSON")
    p.set_defaults(run=run)


def _truth(path: Path) -> tuple[TruthSeries, np.ndarray]:
    if path.is_dir():
        dataset = Dataset.open(path)
        truth = dataset.truth()
        if truth is None:
            raise ValueError(f"{path}: the dataset has no truth (state_groundtruth_estimate0 or leica0)")
        return truth, dataset.calibration.truth_point_b
    t, p, q = read_tum(path)
    return TruthSeries(t, p, q), np.zeros(3)


def run(args: argparse.Namespace) -> int:
    t, p, q = read_tum(args.trajectory)
    truth, point_b = _truth(Path(args.truth))
    if args.point_b:
        try:
            point_b = np.array([float(x) for x in args.point_b.split(",")])
        except ValueError:
            raise ValueError(f"--point-b {args.point_b!r}: expected three numbers X,Y,Z") from None
        if point_b.shape != (3,):
            raise ValueError(f"--point-b {args.point_b!r}: expected three numbers X,Y,Z")
    scores = evaluate(t, p, q, truth, point_b)
    print(json.dumps(scores, indent=2))
    if args.report:
        write_json(args.report, scores)
    return 0
