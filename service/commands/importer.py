"""``vtolpose import``: external data into the dataset layout."""

from __future__ import annotations

import argparse
import json

from vtolpose.drivers.files.euroc_import import default_mounting_path, import_euroc


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "import",
        help="convert external data (EuRoC) into a dataset",
        description="Convert an external recording into the dataset layout that `replay` reads.\n\n"
        "euroc: an ASL/EuRoC folder (mav0/imu0 and a truth). The truth is --truth FILE (TUM or EuRoC CSV:\n"
        "the IMU's pose on the IMU clock) or the first of mav0/state_groundtruth_estimate0, leica0, vicon0;\n"
        "with --gps-rate a GPS is made from it the way the thesis made its GPS (subsampled, Gaussian\n"
        "noise with sigma_z^2 = 2 sigma_xy^2). mav0/cam0 (images, intrinsics, distortion, mounting) comes\n"
        "along unless --no-camera. The IMU mounting comes from --mounting, the same file for every flight.\n\n"
        "Examples:\n"
        "  vtolpose import euroc ../shared/data/euroc_mh01 --out data/mh01 --gps-rate 10 --gps-sigma 0.02\n"
        "  vtolpose import euroc ../shared/data/euroc_dev/V101 --truth ../shared/data/euroc_dev/V101/truth.tum \\\n"
        "      --out data/v101 --gps-rate 10 --seed 1",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("format", choices=("euroc",), help="source format")
    p.add_argument("src", metavar="SRC", help="source folder")
    p.add_argument("--out", required=True, metavar="DATASET")
    p.add_argument("--gps-rate", type=float, metavar="HZ", help="make a GPS stream at this rate from the position track")
    p.add_argument("--gps-sigma", type=float, default=0.02, metavar="M", help="horizontal GPS sigma [m] (default 0.02)")
    p.add_argument("--seed", type=int, default=0, help="GPS noise seed (default 0)")
    p.add_argument("--mounting", metavar="YAML", help=f"IMU mounting and truth frame (default {default_mounting_path().name})")
    p.add_argument("--truth", metavar="FILE", help="truth as a TUM (or EuRoC CSV) file: the IMU's pose, IMU clock")
    p.add_argument("--no-camera", action="store_true", help="leave mav0/cam0 out")
    p.add_argument("--force", action="store_true", help="replace an existing dataset in --out")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    summary = import_euroc(
        args.src, args.out, gps_rate_hz=args.gps_rate, gps_sigma_m=args.gps_sigma, seed=args.seed,
        mounting=args.mounting, overwrite=args.force, truth_file=args.truth, camera=not args.no_camera,
    )
    print(json.dumps(summary, indent=2))
    return 0
