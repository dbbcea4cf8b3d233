"""``vtolpose calibrate camera`` (chessboard intrinsics) and ``calibrate timesync`` (IMU–camera offset)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from vtolpose.service.calibration.options import add_output_options

if TYPE_CHECKING:
    import numpy as np

    from vtolpose.estimator import Board, ChessboardCalibration

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm"}


def add_parsers(jobs: argparse._SubParsersAction) -> None:
    cam = jobs.add_parser(
        "camera", help="intrinsics and distortion from chessboard images (OpenCV)",
        description="Camera intrinsics and radial-tangential distortion from chessboard views (thesis 5.3),\n"
        "with the RMS reprojection error and the views worth dropping.\n\n"
        "Examples:\n"
        "  vtolpose calibrate camera shots/ --board 9x6 --square 0.025\n"
        "  vtolpose calibrate camera shots/*.png --board 9x6 --square 0.025 --drop --out camera.yaml")
    cam.add_argument("images", nargs="+", metavar="IMAGE", help="chessboard images, or folders of them")
    cam.add_argument("--board", required=True, metavar="COLSxROWS", help="inner corners of the board, e.g. 9x6")
    cam.add_argument("--square", required=True, type=float, metavar="M", help="side of one square [m]")
    cam.add_argument("--min-views", type=int, default=8, metavar="N", help="fewest usable views (default 8)")
    cam.add_argument("--drop", action="store_true", help="calibrate again without the views flagged to drop")
    add_output_options(cam, "calib_camera")
    cam.set_defaults(run=run_camera)

    sync = jobs.add_parser(
        "timesync", help="IMU-camera time offset by correlating gyro and camera rotation",
        description="The camera's time offset against the IMU clock (thesis 5.1.2): the lag that best correlates\n"
        "the gyro's rate with the rotation seen between frames. Swing the camera about all axes.\n\n"
        "Examples:\n"
        "  vtolpose calibrate timesync data/book\n"
        "  vtolpose calibrate timesync data/book --max-offset 0.1 --out timesync.yaml")
    sync.add_argument("dataset", metavar="DATASET", help="a dataset with IMU and camera frames (mav0/cam0)")
    sync.add_argument("--max-offset", type=float, default=0.2, metavar="S", help="scan ± this (default 0.2 s)")
    sync.add_argument("--step", type=float, default=0.001, metavar="S", help="scan step (default 0.001 s)")
    add_output_options(sync, "calib_timesync")
    sync.set_defaults(run=run_timesync)


def parse_board(text: str, square_m: float) -> Board:
    from vtolpose.estimator import Board

    try:
        cols, rows = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--board {text!r}: expected inner corners as COLSxROWS, e.g. 9x6") from None
    return Board(cols, rows, square_m)


def image_paths(items: list[str]) -> list[Path]:
    paths: list[Path] = []
    for item in items:
        path = Path(item)
        if path.is_dir():
            paths += sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        elif path.is_file():
            paths.append(path)
        else:
            raise FileNotFoundError(f"{path}: no such image or folder")
    if not paths:
        raise ValueError(f"no images ({', '.join(sorted(IMAGE_SUFFIXES))}) in {', '.join(items)}")
    return paths


def detect(paths: list[Path], board: Board) -> tuple[list[tuple[str, np.ndarray]], list[str], tuple[int, int]]:
    """Corners of every view where the whole board is found; the names where it is not; the image size."""
    import cv2  # on first use: a process that never needs OpenCV never loads it (~16 MB)

    from vtolpose.estimator import find_corners

    views, missing, size = [], [], None
    for path in paths:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            log.warning("%s: not a readable image; skipped", path)
            missing.append(path.name)
            continue
        this = (image.shape[1], image.shape[0])
        if size is None:
            size = this
        elif this != size:
            raise ValueError(f"{path}: {this[0]}x{this[1]} px, but the first image is {size[0]}x{size[1]}: "
                             "calibrate one camera mode at a time")
        corners = find_corners(image, board)
        if corners is None:
            missing.append(path.name)
        else:
            views.append((path.name, corners))
    return views, missing, size or (0, 0)


def _summary(cal: ChessboardCalibration, missing: list[str]) -> list[str]:
    K, s = cal.K, cal.intrinsic_sigma
    lines = [
        f"camera {cal.width}x{cal.height}: fx {K[0, 0]:.2f} +- {s[0]:.2f}, fy {K[1, 1]:.2f} +- {s[1]:.2f}, "
        f"cx {K[0, 2]:.2f} +- {s[2]:.2f}, cy {K[1, 2]:.2f} +- {s[3]:.2f} px",
        "distortion k1 k2 p1 p2 k3: " + " ".join(f"{x:+.5f}" for x in cal.distortion),
        f"RMS reprojection error: {cal.rms_px:.3f} px over {len(cal.view_names)} views",
        "per view [px]: " + ", ".join(f"{n} {r:.3f}" for n, r in zip(cal.view_names, cal.view_rms_px)),
        "views to drop: " + (", ".join(cal.drop) if cal.drop else "none"),
    ]
    if missing:
        lines.append(f"board not found in {len(missing)} image(s): {', '.join(missing)}")
    return lines


def run_camera(args: argparse.Namespace) -> int:
    from vtolpose.estimator import calibrate_views, ChessboardError
    from vtolpose.service.calibration import output as out

    board = parse_board(args.board, args.square)
    paths = image_paths(args.images)
    views, missing, size = detect(paths, board)
    try:
        cal = calibrate_views(views, board, size, min_views=args.min_views)
    except ChessboardError as exc:
        where = f" (not found in {len(missing)} of {len(paths)} images: {', '.join(missing[:10])}" + \
            (", ..." if len(missing) > 10 else "") + ")" if missing else ""
        raise ChessboardError(f"{exc}{where}") from None
    summary = _summary(cal, missing)
    if args.drop and cal.drop:
        kept = [v for v in views if v[0] not in cal.drop]
        cal = calibrate_views(kept, board, size, min_views=args.min_views)
        summary += ["", f"again without the {len(views) - len(kept)} dropped view(s):"] + _summary(cal, [])
    header = [f"vtolpose calibrate camera ({len(paths)} images, board {args.board}, square {args.square:g} m)",
              *summary[:3], "dataset.yaml form (add R_BC, t_BC, rate_hz):", out.dataset_camera_block(cal)]
    text = out.config_block(out.camera_tree(cal), header)

    def draw(path: Path) -> None:
        from vtolpose.service.calibration.plots import plot_reprojection

        plot_reprojection(path, cal)

    return out.finish(args, text, summary, draw)


def run_timesync(args: argparse.Namespace) -> int:
    import numpy as np

    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.estimator import TimeSyncOptions
    from vtolpose.service.calibration import output as out
    from vtolpose.service.calibration.timesync import measure

    dataset = Dataset.open(args.dataset)
    camera = dataset.calibration.camera
    m = measure(dataset, TimeSyncOptions(max_offset_s=args.max_offset, step_s=args.step))
    r, rotations = m.result, m.rotations
    summary = [
        f"camera time offset (added to the frame stamps to put them on the IMU clock): {r.offset_s * 1e3:+.2f} ms "
        f"+- {r.sigma_s * 1e3:.2f} ms",
        f"correlation peak {r.peak:.3f} over {r.n_pairs} frame pairs ({rotations.frames} frames, "
        f"{rotations.pairs_skipped} pairs without enough tracks); camera turned at {np.degrees(r.rate_rms):.1f} deg/s RMS",
        f"camera vs gyro rotation per pair: {r.residual_rms * 1e3:.2f} mrad RMS per axis",
        f"relative to the stamps in cam0/data.csv; dataset.yaml now says camera.time_offset_s: {camera.time_offset_s:g}",
    ]
    header = [f"vtolpose calibrate timesync {args.dataset}", *summary,
              f"dataset.yaml form: camera: time_offset_s: {r.offset_s:.6f} (the estimator adds it to every frame stamp)"]
    text = out.config_block(out.camera_offset_tree(r.offset_s), header)

    def draw(path: Path) -> None:
        from vtolpose.service.calibration.plots import plot_correlation

        plot_correlation(path, r)

    return out.finish(args, text, summary, draw)
