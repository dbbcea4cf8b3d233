"""``vtolpose import``: external data into the dataset layout."""

from __future__ import annotations

import argparse
from pathlib import Path

from vtolpose.drivers.files.euroc_import import default_mounting_path, import_euroc
from vtolpose.service.text import field_lines


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "import",
        help="convert external data (EuRoC) into a dataset",
        description="Convert an external recording into the dataset layout that `replay` reads.\n\n"
        "euroc: an ASL/EuRoC folder (mav0/imu0, mav0/leica0). The Leica track becomes position truth;\n"
        "with --gps-rate a GPS is made from it the way the thesis made its GPS (subsampled, Gaussian\n"
        "noise with sigma_z^2 = 2 sigma_xy^2). The IMU mounting comes from --mounting.\n\n"
        "Example:\n"
        "  vtolpose import euroc ../shared/data/euroc_mh01 --out data/mh01 --gps-rate 10 --gps-sigma 0.02",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("format", choices=("euroc",), help="source format")
    p.add_argument("src", metavar="SRC", help="source folder")
    p.add_argument("--out", required=True, metavar="DATASET")
    p.add_argument("--gps-rate", type=float, metavar="HZ", help="make a GPS stream at this rate from the position track")
    p.add_argument("--gps-sigma", type=float, default=0.02, metavar="M", help="horizontal GPS sigma [m] (default 0.02)")
    p.add_argument("--seed", type=int, default=0, help="GPS noise seed (default 0)")
    p.add_argument("--mounting", metavar="YAML", help=f"IMU mounting and truth frame (default {default_mounting_path().name})")
    p.add_argument("--force", action="store_true", help="replace an existing dataset in --out")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    src = Path(args.src)
    if not src.is_dir():
        raise FileNotFoundError(f"{src}: no such folder (expected an ASL/EuRoC folder holding mav0/)")
    if not (src / "mav0").is_dir():
        raise FileNotFoundError(f"{src}: not an ASL/EuRoC folder (it has no mav0/)")
    summary = import_euroc(
        args.src, args.out, gps_rate_hz=args.gps_rate, gps_sigma_m=args.gps_sigma, seed=args.seed,
        mounting=args.mounting, overwrite=args.force,
    )
    print(f"imported {args.src} into {args.out}")
    for line in field_lines(summary):
        print(line)
    return 0
