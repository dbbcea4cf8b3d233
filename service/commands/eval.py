"""``vtolpose eval``: score any TUM or EuRoC trajectory against truth."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from vtolpose.service.commands.common import write_json
from vtolpose.service.text import number

if TYPE_CHECKING:
    import numpy as np

    from vtolpose.drivers.files.series import TruthSeries


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
    import numpy as np

    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.drivers.files.series import TruthSeries
    from vtolpose.drivers.files.tum import read_tum

    if not path.exists():
        raise FileNotFoundError(f"{path}: truth not found (--truth takes a dataset folder or a TUM / EuRoC truth file)")
    if path.is_dir():
        dataset = Dataset.open(path)
        truth = dataset.truth()
        if truth is None:
            raise ValueError(f"{path}: the dataset has no truth (state_groundtruth_estimate0 or leica0)")
        return truth, dataset.calibration.truth_point_b
    t, p, q = read_tum(path)
    return TruthSeries(t, p, q), np.zeros(3)


def score_lines(trajectory: str, truth: str, s: dict) -> list[str]:
    """The scores as a person reads them (the --report JSON keeps every digit)."""
    n, e, d = s["position_rmse_ned_m"]
    lines = [
        f"{trajectory} against {truth}: {s['samples']} truth samples over {number(s['duration_s'])} s"
        + (f" ({s['truth_samples_outside_estimate']} outside the estimate's time span, not scored)"
           if s["truth_samples_outside_estimate"] else ""),
        f"  position RMSE {s['position_rmse_m']:.4f} m (N {n:.4f}, E {e:.4f}, D {d:.4f}), max {s['max_position_error_m']:.4f} m",
    ]
    if s.get("attitude_rmse_deg") is not None:
        lines.append(f"  attitude RMSE {s['attitude_rmse_deg']:.3f} deg, max {s['max_attitude_error_deg']:.3f} deg")
    drift = f"  final drift {s['final_drift_m']:.4f} m"
    if s.get("distance_travelled_m"):
        drift += f" ({s['drift_percent']:.2f} % of {s['distance_travelled_m']:.1f} m travelled)"
    return lines + [drift]


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from vtolpose.drivers.files.tum import read_tum
    from vtolpose.estimator import evaluate

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
    for line in score_lines(args.trajectory, args.truth, scores):
        print(line)
    if args.report:
        write_json(args.report, scores)
    return 0
