"""``vtolpose import``: external data into the dataset layout."""

from __future__ import annotations

import argparse
from pathlib import Path

from vtolpose.service.text import field_lines

MOUNTING_NAME = "euroc_vi_sensor.yaml"  # euroc_import's default mounting file, named here so --help loads no importer


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "import",
        help="convert external data (EuRoC, ROS 2 bags) into a dataset",
        description="Convert an external recording into the dataset layout that `replay` reads.\n\n"
        "euroc: an ASL/EuRoC folder (mav0/imu0, a truth if it has one). The truth is --truth FILE (TUM or\n"
        "EuRoC CSV: the IMU's pose on the IMU clock) or the first of mav0/state_groundtruth_estimate0,\n"
        "leica0, vicon0; a recording with none (a flight of your own) imports without, and its replays\n"
        "report no scores. With --gps-rate a GPS is made from the truth the way the thesis made its GPS\n"
        "(subsampled, Gaussian noise with sigma_z^2 = 2 sigma_xy^2). mav0/cam0 (PNG or JPEG images at any\n"
        "resolution, kept as they are; intrinsics, distortion, mounting) comes along unless --no-camera.\n"
        "The IMU mounting comes from --mounting, the same file for every flight of one rig.\n"
        "--truth FILE takes the truth from a TUM file instead (the IMU's pose on the IMU clock).\n\n"
        "rosbag: a ROS 2 bag (rosbag2 folder with sqlite3 or MCAP storage, or a .mcap file): --imu\n"
        "(sensor_msgs/Imu) and --gps (NavSatFix), optionally --image (Image or CompressedImage, needs\n"
        "--calibration with a camera) and --truth TOPIC (PoseStamped or Odometry, ENU/FLU). Header stamps\n"
        "are the times. The calibration comes from --calibration (a dataset.yaml-format file), else\n"
        "from the bag: IMU axes = base_link (FLU), noise from the messages' covariances.\n\n"
        "Examples:\n"
        "  vtolpose import euroc ../shared/data/euroc_mh01 --out data/mh01 --gps-rate 10 --gps-sigma 0.02\n"
        "  vtolpose import euroc ../shared/data/euroc_dev/V101 --truth ../shared/data/euroc_dev/V101/truth.tum \\\n"
        "      --out data/v101 --gps-rate 10 --seed 1\n"
        "  vtolpose import rosbag flight_bag --imu /imu/data --gps /fix --image /camera/image_raw \\\n"
        "      --calibration vehicle_calibration.yaml --out data/flight",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("format", choices=("euroc", "rosbag"), help="source format")
    p.add_argument("src", metavar="SRC", help="source folder (or, for rosbag, a .mcap file)")
    p.add_argument("--out", required=True, metavar="DATASET")
    p.add_argument("--gps-rate", type=float, metavar="HZ", help="make a GPS stream at this rate from the position track")
    p.add_argument("--gps-sigma", type=float, default=0.02, metavar="M", help="horizontal GPS sigma [m] (default 0.02)")
    p.add_argument("--seed", type=int, default=0, help="GPS noise seed (default 0)")
    p.add_argument("--mounting", metavar="YAML", help=f"IMU mounting and truth frame (default {MOUNTING_NAME})")
    p.add_argument("--truth", metavar="FILE|TOPIC", help="euroc: truth as a TUM (or EuRoC CSV) file, the IMU's pose on "
                   "the IMU clock; rosbag: a geometry_msgs/PoseStamped or nav_msgs/Odometry topic")
    p.add_argument("--no-camera", action="store_true", help="euroc: leave mav0/cam0 out")
    sync = p.add_mutually_exclusive_group()
    sync.add_argument("--camera-time-offset", type=float, metavar="S",
                      help="euroc: the camera's offset against the IMU clock, added to every frame stamp [s] (from "
                      "your calibration); without it the import measures it (gyro against frame rotation)")
    sync.add_argument("--no-timesync", action="store_true",
                      help="euroc: take the frame stamps as they are (offset 0), measuring nothing")
    p.add_argument("--force", action="store_true", help="replace an existing dataset in --out")
    bag = p.add_argument_group("rosbag")
    bag.add_argument("--imu", metavar="TOPIC", help="sensor_msgs/Imu topic (required for rosbag)")
    bag.add_argument("--gps", metavar="TOPIC", help="sensor_msgs/NavSatFix topic (required for rosbag)")
    bag.add_argument("--image", metavar="TOPIC", help="sensor_msgs/Image or CompressedImage topic")
    bag.add_argument("--calibration", metavar="YAML", help="the vehicle's calibration (dataset.yaml format)")
    bag.add_argument("--fix-sigma", metavar="H[,V]", help="GPS 1-sigma [m] for fixes without a covariance (V: 2 H if not given)")
    p.set_defaults(run=run)


def _fix_sigma(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        values = []
    if len(values) not in (1, 2) or not all(v > 0.0 for v in values):
        raise ValueError(f"--fix-sigma {text!r}: expected H or H,V, positive metres")
    return values[0], values[1] if len(values) == 2 else 2.0 * values[0]


def run(args: argparse.Namespace) -> int:
    if args.format == "rosbag":
        from vtolpose.drivers.files.rosbag_import import import_rosbag

        if not args.imu or not args.gps:
            raise ValueError("import rosbag needs --imu TOPIC and --gps TOPIC")
        if not Path(args.src).exists():
            raise FileNotFoundError(f"{args.src}: no such bag (a rosbag2 folder or a .mcap file)")
        summary = import_rosbag(args.src, args.out, args.imu, args.gps, args.image, args.truth, args.calibration,
                                _fix_sigma(args.fix_sigma), overwrite=args.force)
    else:
        from vtolpose.drivers.files.euroc_import import import_euroc

        src = Path(args.src)
        if not src.is_dir():
            raise FileNotFoundError(f"{src}: no such folder (expected an ASL/EuRoC folder holding mav0/)")
        if not (src / "mav0").is_dir():
            raise FileNotFoundError(f"{src}: not an ASL/EuRoC folder (it has no mav0/)")
        summary = import_euroc(
            args.src, args.out, gps_rate_hz=args.gps_rate, gps_sigma_m=args.gps_sigma, seed=args.seed,
            mounting=args.mounting, overwrite=args.force, truth_file=args.truth, camera=not args.no_camera,
        )
    if args.format == "euroc" and summary.get("camera_frames"):
        summary["camera_time_offset"] = settle_camera_time_offset(Path(args.out), args.camera_time_offset, args.no_timesync)
    print(f"imported {args.src} into {args.out}")
    for line in field_lines(summary):
        print(line)
    return 0


def settle_camera_time_offset(out: Path, given: float | None, keep_stamps: bool) -> str:
    """The camera's time offset written into the imported dataset: given, or measured on its own frames and
    gyro (an ASL/EuRoC folder has no field for it, and a replay whose frames are stamped tens of milliseconds
    late gets lost); what was done, as one line for the summary."""
    from vtolpose.drivers.files.dataset import Dataset, set_camera_time_offset
    from vtolpose.service.calibration.timesync import describe, measure, SIGNIFICANT_SIGMAS

    if keep_stamps:
        return "0 (--no-timesync: the frame stamps taken as they are)"
    if given is not None:
        set_camera_time_offset(out, given, f"camera time offset {given * 1e3:+.2f} ms as given (--camera-time-offset)")
        return f"{given * 1e3:+.2f} ms, as given"
    print("measuring the camera's time offset against the IMU clock (gyro against frame rotation) ...", flush=True)
    try:
        m = measure(Dataset.open(out))
    except ValueError as exc:  # TimeSyncError: the recording cannot show it
        return (f"0, not measured: {exc}. The frame stamps are taken as they are; give the offset with "
                "--camera-time-offset S, or measure it on a recording made for it (vtolpose calibrate timesync)")
    if not m.significant:
        return (f"0: measured {describe(m)}, within {SIGNIFICANT_SIGMAS:g} sigma of zero: the frame stamps are "
                "taken as they are")
    set_camera_time_offset(out, round(m.result.offset_s, 6), f"camera time offset {describe(m)}, measured at import")
    return f"{describe(m)}, measured and written to dataset.yaml (camera: time_offset_s)"

