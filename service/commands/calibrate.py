"""``vtolpose calibrate``: the thesis' chapter 5 as one command per job.

Each job reads a recording, prints what it measured, writes a configuration block that
``--config`` accepts as it is, and draws a figure to check it by eye. When the recording cannot
give the figure (no rest, too few chessboard views, too little motion) it says what to record
instead and writes nothing.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from vtolpose.service.calibration.options import add_output_options
from vtolpose.service.commands import calibrate_camera

if TYPE_CHECKING:
    import numpy as np

    from vtolpose.drivers.files.dataset import Dataset

REST_BIAS_SIGMA = 0.005  # rad/s: how far a gyro bias measured at rest may wander during a flight of minutes


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate",
        help="calibrate IMU, camera, IMU-camera and GPS timing, GPS lever arm",
        description="Sensor calibration (thesis chapter 5). Each job writes a YAML block for --config and a PNG.\n\n"
        "Examples:\n"
        "  vtolpose calibrate imu data/mh01\n"
        "  vtolpose calibrate camera shots/ --board 9x6 --square 0.025\n"
        "  vtolpose calibrate timesync data/book\n"
        "  vtolpose calibrate gps-latency data/mh01\n"
        "  vtolpose calibrate lever-arm data/mh01 --offset 0.0",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    jobs = p.add_subparsers(dest="job", metavar="JOB", required=True)

    imu = jobs.add_parser(
        "imu", help="gravity, gyro bias, roll/pitch and Allan noise figures from a rest stretch",
        description="IMU calibration from the longest stretch at rest (thesis 5.2): |f| (the thesis' g), gyro bias,\n"
        "roll and pitch, and the Allan deviation's white noise, bias instability and random walk.\n"
        "The rest must last --min-static seconds; minutes give the noise figures, an hour the random walk.\n\n"
        "Examples:\n"
        "  vtolpose calibrate imu data/mh01\n"
        "  vtolpose simulate --rest 600 --duration 610 --no-camera --out data/rest && vtolpose calibrate imu data/rest")
    imu.add_argument("dataset", metavar="DATASET")
    imu.add_argument("--min-static", type=float, default=10.0, metavar="S", help="shortest rest stretch to use (default 10 s)")
    imu.add_argument("--min-tau", type=float, default=0.0, metavar="S",
                     help="leave cluster times below this out of the Allan fit (a sensor's internal filter)")
    add_output_options(imu, "calib_imu")
    imu.set_defaults(run=run_imu)

    calibrate_camera.add_parsers(jobs)

    for name, helptext, example in (
        ("gps-latency", "time offset of the GPS (or truth track) against the IMU clock",
         "  vtolpose calibrate gps-latency data/mh01\n"
         "  vtolpose calibrate gps-latency data/mh01 --source truth --plot latency.png"),
        ("lever-arm", "GPS antenna lever arm in the body frame",
         "  vtolpose calibrate lever-arm data/mh01 --offset -0.142\n"
         "  vtolpose calibrate lever-arm data/mh01 --source truth --out lever.yaml"),
    ):
        g = jobs.add_parser(name, help=helptext, description=f"{helptext[0].upper()}{helptext[1:]}, from in-motion "
                            f"alignment fits over the liveliest windows of the flight.\n\nExamples:\n{example}")
        g.add_argument("dataset", metavar="DATASET")
        g.add_argument("--source", choices=("gps", "truth"), default="gps",
                       help="position track to use: the dataset's GPS, or its truth track (e.g. the raw Leica)")
        g.add_argument("--sigma", type=float, default=0.005, metavar="M", help="position sigma of the truth track (default 0.005 m)")
        g.add_argument("--window", type=float, default=7.0, metavar="S", help="fit window length (default 7 s)")
        g.add_argument("--windows", type=int, default=7, metavar="N", help="how many windows (default 7, the liveliest)")
        if name == "gps-latency":
            g.add_argument("--max-offset", type=float, default=0.3, metavar="S", help="scan ± this (default 0.3 s)")
            g.add_argument("--centre", type=float, default=0.0, metavar="S", help="around this offset (default 0)")
            g.add_argument("--step", type=float, default=0.01, metavar="S", help="scan step (default 0.01 s)")
            g.set_defaults(run=run_gps_latency)
        else:
            g.add_argument("--offset", type=float, default=0.0, metavar="S",
                           help="time offset of the fixes, from gps-latency (default 0)")
            g.set_defaults(run=run_lever_arm)
        add_output_options(g, "calib_" + name.replace("-", "_"), figure=name == "gps-latency")


def _seconds(t_ns: int, t0_ns: int) -> float:
    return (t_ns - t0_ns) * 1e-9


def _positions(dataset: Dataset) -> tuple[np.ndarray, np.ndarray] | None:
    """Fix times and positions (GPS, else truth) that can tell rest from steady flight."""
    gps = dataset.gps()
    if gps is not None:
        return gps.t_ns, gps.p_ned
    truth = dataset.truth()
    return None if truth is None else (truth.t_ns, truth.p)


def run_imu(args: argparse.Namespace) -> int:
    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.estimator import calibrate_imu, StaticOptions
    from vtolpose.service.calibration import output as out

    dataset = Dataset.open(args.dataset)
    imu = dataset.imu()
    static = StaticOptions(min_duration_s=args.min_static, gravity=dataset.calibration.imu.gravity)
    r = calibrate_imu(imu.t_ns, imu.gyro, imu.accel, static, args.min_tau, _positions(dataset))
    t0 = int(imu.t_ns[0])
    s = r.stretch
    others = ", ".join(f"{_seconds(x.t0_ns, t0):.1f}-{_seconds(x.t1_ns, t0):.1f} s" for x in r.stretches[1:])

    def axes(v: np.ndarray | None) -> str:
        return "not measurable (see notes)" if v is None else "[" + ", ".join(f"{x:.3e}" for x in v) + "]"

    summary = [
        f"static stretch: {_seconds(s.t0_ns, t0):.1f}-{_seconds(s.t1_ns, t0):.1f} s of the record ({s.duration_s:.1f} s, "
        f"{r.rate_hz:.1f} Hz)" + (f"; also at rest: {others}" if others else ""),
        f"gravity |f|: {r.gravity:.5f} m/s^2 (dataset nominal {dataset.calibration.imu.gravity:.5f})",
        f"gyro bias [rad/s]: {axes(r.gyro_bias)} +- {axes(r.gyro_bias_sigma)}",
        f"roll, pitch at rest: {math.degrees(r.roll_rad):.3f} deg, {math.degrees(r.pitch_rad):.3f} deg",
        f"gyro white noise [rad/s/sqrt(Hz)]: {axes(r.figure('gyro', 'white_noise'))}",
        f"gyro bias instability [rad/s]: {axes(r.figure('gyro', 'bias_instability'))}",
        f"gyro bias random walk [rad/s^2/sqrt(Hz)]: {axes(r.figure('gyro', 'random_walk'))}",
        f"accel white noise [m/s^2/sqrt(Hz)]: {axes(r.figure('accel', 'white_noise'))}",
        f"accel bias instability [m/s^2]: {axes(r.figure('accel', 'bias_instability'))}",
        f"accel bias random walk [m/s^3/sqrt(Hz)]: {axes(r.figure('accel', 'random_walk'))}",
    ] + [f"note: {n}" for n in r.notes]
    header = [f"vtolpose calibrate imu {args.dataset}", *summary[:1],
              "estimator.imu.noise: the largest axis of each figure; null = not measured (the dataset's stands).",
              "Rest figures: a vehicle vibrating in flight has more white noise (see config/euroc_vi_sensor.yaml)."]
    header += [f"note: {n}" for n in r.notes]
    text = out.config_block(out.imu_tree(r), header)

    def draw(path: Path) -> None:
        from vtolpose.service.calibration.plots import plot_allan

        plot_allan(path, r)

    return out.finish(args, text, summary, draw)


def _track(dataset: Dataset, args: argparse.Namespace):
    """Fix times, NED positions, σ (N, 3) and the lever arm of the tracked point."""
    import numpy as np

    if args.source == "gps":
        gps = dataset.gps()
        if gps is None:
            raise ValueError(f"{args.dataset}: the dataset has no GPS (mav0/gps0); use --source truth for its truth track")
        sigma = np.column_stack([gps.sigma_h, gps.sigma_h, gps.sigma_v])
        return gps.t_ns, gps.p_ned, sigma, dataset.calibration.gps.lever_arm_b
    truth = dataset.truth()
    if truth is None:
        raise ValueError(f"{args.dataset}: the dataset has no truth track (state_groundtruth_estimate0 or leica0)")
    return truth.t_ns, truth.p, np.full((len(truth.t_ns), 3), args.sigma), dataset.calibration.truth_point_b


def _gps_setup(args: argparse.Namespace):
    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.estimator import find_static_stretches, GpsCalibOptions, StaticOptions

    dataset = Dataset.open(args.dataset)
    imu = dataset.imu()
    t, p, sigma, lever = _track(dataset, args)
    # A gyro bias measured at rest keeps the short fit windows from trading it against attitude.
    rest = find_static_stretches(imu.t_ns, imu.gyro, imu.accel,
                                 StaticOptions(min_duration_s=5.0, gravity=dataset.calibration.imu.gravity))
    prior = imu.gyro[rest[0].start:rest[0].stop].mean(axis=0) if rest else None
    options = GpsCalibOptions(window_s=args.window, windows=args.windows)
    if prior is not None:
        options = replace(options, sigma_gyro_bias=REST_BIAS_SIGMA)
    return dataset, imu, (t, p, sigma), lever, prior, options


def run_gps_latency(args: argparse.Namespace) -> int:
    from vtolpose.estimator import scan_latency
    from vtolpose.service.calibration import output as out

    dataset, imu, (t, p, sigma), lever, prior, options = _gps_setup(args)
    options = replace(options, max_offset_s=args.max_offset, centre_s=args.centre, step_s=args.step)
    scan = scan_latency(imu.t_ns, imu.gyro, imu.accel, t, p, sigma, dataset.calibration.imu.gravity, lever, options, prior)
    t0 = int(imu.t_ns[0])
    what = "GPS" if args.source == "gps" else "truth track"
    summary = [
        f"{what} time offset (added to its stamps to put them on the IMU clock): {scan.offset_s * 1e3:+.1f} ms "
        f"+- {scan.sigma_s * 1e3:.1f} ms (latency {-scan.offset_s * 1e3:+.1f} ms)",
        "windows (start s: own best offset ms): " + ", ".join(
            f"{_seconds(a, t0):.1f}: {o * 1e3:+.0f}" for (a, _), o in zip(scan.windows, scan.window_offsets_s)),
        f"residual at the best offset: {scan.residual_ratio:.2f} x the stated position noise ({scan.n_fixes} fixes)",
        f"gyro bias prior: {'from the rest stretch' if prior is not None else 'none (no rest stretch of 5 s)'}",
    ]
    header = [f"vtolpose calibrate gps-latency {args.dataset} --source {args.source}", *summary[:3],
              "Relative to the stamps as stored in this dataset."]
    text = out.config_block(out.gps_tree(time_offset_s=scan.offset_s), header)

    def draw(path: Path) -> None:
        from vtolpose.service.calibration.plots import plot_latency

        plot_latency(path, scan, what)

    return out.finish(args, text, summary, draw)


def run_lever_arm(args: argparse.Namespace) -> int:
    from vtolpose.estimator import fit_lever_arm
    from vtolpose.service.calibration import output as out

    dataset, imu, (t, p, sigma), lever, prior, options = _gps_setup(args)
    fit = fit_lever_arm(imu.t_ns, imu.gyro, imu.accel, t, p, sigma, dataset.calibration.imu.gravity, args.offset,
                        None, options, prior)
    summary = [
        f"lever arm (body FRD) [m]: [{', '.join(f'{x:+.4f}' for x in fit.lever_arm_b)}] "
        f"+- [{', '.join(f'{x:.4f}' for x in fit.sigma_m)}]",
        f"dataset states: [{', '.join(f'{x:+.4f}' for x in lever)}]",
        f"residual: {fit.residual_ratio:.2f} x the stated position noise ({fit.n_fixes} fixes in {len(fit.windows)} "
        f"windows, time offset {args.offset * 1e3:+.1f} ms)",
    ]
    header = [f"vtolpose calibrate lever-arm {args.dataset} --source {args.source} --offset {args.offset:g}", *summary,
              "In dataset.yaml this is gps: lever_arm_b (or truth: point_b for a truth track)."]
    text = out.config_block(out.gps_tree(lever_arm_b=fit.lever_arm_b), header)
    return out.finish(args, text, summary, lambda path: None)  # three numbers: no figure needed

