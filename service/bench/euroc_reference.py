"""Replay speed against a reference on the same inputs, measured in the same run (the same machine, the same load).

The reference is GTSAM (optional extra ``bench``, never imported at run time): the IMU
preintegrated between GPS fixes (``CombinedImuFactor``: attitude, velocity, position and both
biases), one GPS factor with the antenna's lever arm per fix, the states at the fixes, in an
incremental fixed-lag smoother with a 3-s lag. It is given what vtolpose has to find for
itself — the truth's attitude at its first state (else level from the accelerometer) — because
it is a yardstick for speed, not for start-up. Both run on the same imported flight (the IMU as
recorded in body axes, the 10-Hz GPS of ``service.bench.euroc``), one after the other in one
process, in turn, three times, each side's best run counting (a replay is deterministic: its runs differ
only by what the machine was doing); the figure that matters is the ratio of their real-time factors.

Then accuracy, both sides scored alike (:func:`accuracy_rows`). The reference's own RMSE is taken right
after each of its updates only; a service built on it would publish, between fixes, the fix's state
carried forward by the IMU (:func:`causal_trajectory`), and that trajectory is scored here as
``vtolpose bench --only euroc`` scores vtolpose's: every truth sample, after the rigid alignment. The
reference runs with the vehicle file's IMU noise (vtolpose's) and, once more, with the recording's own
``sensor.yaml`` (the IMU's static datasheet figures).
"""

from __future__ import annotations

import importlib
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from vtolpose.config import load_config
from vtolpose.drivers.files.calibration_yaml import CalibrationError, load_yaml_file
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.estimator import rot_to_quat
from vtolpose.service.bench.euroc import (
    VARIANTS, at_fix_position_rmse, flights_or_skip, imported_flight, scored_gps_rmse, scored_position_rmse,
)
from vtolpose.service.bench.rows import Row
from vtolpose.service.replay.session import Trajectory, replay
from vtolpose.service.runtime.kernels import load_compiled_kernels

LAG_S = 3.0
REPLAY_TARGET = ">= 250"  # x real time, IMU+GPS, both variants (an hour of flight in under 15 s)
RATIO_TARGET = ">= 4"  # vtolpose's real-time factor over the reference's
ROUNDS = 3  # each side's best of this many runs, taken in turn: the machine's swings are not the code's
_ACCEL_INIT_S = 0.5  # level from the mean specific force over this long when the truth has no attitude


def _level_quaternion(accel_mean: np.ndarray) -> np.ndarray:
    """Body→world (NED) attitude with zero yaw whose "down" matches the measured specific force (w first)."""
    fx, fy, fz = (-accel_mean / np.linalg.norm(accel_mean)).tolist()  # gravity's direction in the body
    roll, pitch = np.arctan2(fy, fz), np.arctan2(-fx, np.hypot(fy, fz))
    cr, sr, cp, sp = np.cos(roll / 2), np.sin(roll / 2), np.cos(pitch / 2), np.sin(pitch / 2)
    return np.array([cr * cp, sr * cp, cr * sp, -sr * sp])


def reference_run(gtsam: Any, dataset: Dataset, causal: bool = False,
                  white: tuple[float, float] | None = None) -> dict[str, Any]:
    """Run the reference over the dataset's IMU and GPS; its wall time, the data's span and its position RMSE
    (the newest state after each fix, tracked point against the truth where there is one). ``causal``: also its
    pose at every IMU sample (:func:`causal_trajectory`, made after the timed run), as ``trajectory``.
    ``white``: the gyroscope's and accelerometer's white-noise densities in place of the vehicle file's."""
    from gtsam.symbol_shorthand import B, V, X

    cal = dataset.calibration
    imu, gps, truth = dataset.imu(), dataset.gps(), dataset.truth()
    noise = cal.imu.noise
    wall0, cpu0 = time.perf_counter(), time.process_time()
    params = gtsam.PreintegrationCombinedParams.MakeSharedD(cal.imu.gravity)  # NED: gravity along +z
    gyro_density, accel_density = (noise.gyro_noise_density, noise.accel_noise_density) if white is None else \
        (np.full(3, white[0]), np.full(3, white[1]))
    params.setGyroscopeCovariance(np.diag(gyro_density**2))
    params.setAccelerometerCovariance(np.diag(accel_density**2))
    params.setIntegrationCovariance(np.eye(3) * 1e-8)
    params.setBiasOmegaCovariance(np.diag(noise.gyro_random_walk**2))
    params.setBiasAccCovariance(np.diag(noise.accel_random_walk**2))
    t_imu, gyro, accel = imu.t_ns, imu.gyro, imu.accel
    t_gps = gps.t_ns[gps.t_ns >= t_imu[0]]
    k0 = int(np.searchsorted(gps.t_ns, t_gps[0]))
    yaw_sigma = 0.05  # rad
    if truth is not None and truth.q is not None:
        q0 = truth.q[min(int(np.searchsorted(truth.t_ns, t_gps[0])), len(truth.t_ns) - 1)]
    else:  # no attitude truth: level, the heading left open
        q0, yaw_sigma = _level_quaternion(accel[t_imu < t_imu[0] + int(_ACCEL_INIT_S * 1e9)].mean(axis=0)), np.pi
    rot0 = gtsam.Rot3.Quaternion(*q0.tolist())
    lever = gtsam.Point3(*cal.gps.lever_arm_b.tolist())
    p0 = gps.p_ned[k0] - rot0.matrix() @ cal.gps.lever_arm_b
    pose, vel, bias = gtsam.Pose3(rot0, gtsam.Point3(*p0.tolist())), np.zeros(3), gtsam.imuBias.ConstantBias()

    smoother = gtsam.IncrementalFixedLagSmoother(LAG_S, gtsam.ISAM2Params())
    graph, values, stamps = gtsam.NonlinearFactorGraph(), gtsam.Values(), gtsam.FixedLagSmootherKeyTimestampMap()
    graph.add(gtsam.PriorFactorPose3(X(0), pose, gtsam.noiseModel.Diagonal.Sigmas(np.array([0.05, 0.05, yaw_sigma, 0.1, 0.1, 0.1]))))
    graph.add(gtsam.PriorFactorVector(V(0), vel, gtsam.noiseModel.Isotropic.Sigma(3, 0.5)))
    graph.add(gtsam.PriorFactorConstantBias(B(0), bias, gtsam.noiseModel.Diagonal.Sigmas(np.r_[[0.1] * 3, [0.01] * 3])))
    values.insert(X(0), pose), values.insert(V(0), vel), values.insert(B(0), bias)
    t0_s = t_gps[0] * 1e-9
    for key in (X(0), V(0), B(0)):
        stamps.insert((key, 0.0))

    gps_sigma = [gtsam.noiseModel.Diagonal.Sigmas(np.array([h, h, v])) for h, v in zip(gps.sigma_h, gps.sigma_v)]
    i = int(np.searchsorted(t_imu, t_gps[0]))
    pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
    estimates = np.zeros((len(t_gps), 3))
    estimates[0] = pose.translation()
    posteriors = [(int(t_gps[0]), pose, vel, bias)]  # each fix's newest state: what it would publish from
    for k in range(1, len(t_gps)):
        t_fix = t_gps[k]
        while i + 1 < len(t_imu) and t_imu[i + 1] <= t_fix:
            pim.integrateMeasurement(accel[i], gyro[i], (t_imu[i + 1] - t_imu[i]) * 1e-9)
            i += 1
        if t_imu[i] < t_fix:  # the last sample held up to the fix
            pim.integrateMeasurement(accel[i], gyro[i], (t_fix - t_imu[i]) * 1e-9)
        graph.add(gtsam.CombinedImuFactor(X(k - 1), V(k - 1), X(k), V(k), B(k - 1), B(k), pim))
        graph.add(gtsam.GPSFactorArm(X(k), gtsam.Point3(*gps.p_ned[k0 + k].tolist()), lever, gps_sigma[k0 + k]))
        predicted = pim.predict(gtsam.NavState(pose, vel), bias)
        values.insert(X(k), predicted.pose()), values.insert(V(k), predicted.velocity()), values.insert(B(k), bias)
        for key in (X(k), V(k), B(k)):
            stamps.insert((key, t_fix * 1e-9 - t0_s))
        smoother.update(graph, values, stamps)
        graph, values, stamps = gtsam.NonlinearFactorGraph(), gtsam.Values(), gtsam.FixedLagSmootherKeyTimestampMap()
        estimate = smoother.calculateEstimate()
        pose, vel, bias = estimate.atPose3(X(k)), estimate.atVector(V(k)), estimate.atConstantBias(B(k))
        estimates[k] = pose.translation() + pose.rotation().matrix() @ cal.truth_point_b
        posteriors.append((int(t_fix), pose, vel, bias))
        pim.resetIntegrationAndSetBias(bias)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    rmse = float("nan")
    if truth is not None:
        inside = (t_gps >= truth.t_ns[0]) & (t_gps <= truth.t_ns[-1])
        p_truth = np.column_stack([np.interp(t_gps[inside], truth.t_ns, truth.p[:, c]) for c in range(3)])
        rmse = float(np.sqrt(np.mean(np.sum((estimates[inside] - p_truth) ** 2, axis=1))))
    out: dict[str, Any] = {"wall_s": wall, "cpu_s": cpu, "duration_s": (int(t_imu[-1]) - int(t_imu[0])) * 1e-9,
                           "rmse_m": rmse}
    if causal:
        out["trajectory"] = causal_trajectory(gtsam, params, posteriors, t_imu, gyro, accel)
    return out


def causal_trajectory(gtsam: Any, params: Any, posteriors: list, t_imu: np.ndarray, gyro: np.ndarray,
                      accel: np.ndarray) -> Trajectory:
    """The reference's pose at each fix and at every IMU sample up to the next fix, from what it knew then: the fix's
    newest state carried forward by the same preintegration its next factor is made of (``predict``). Its own RMSE
    is taken at the fixes only, right after each update; this is the trajectory a service built on it would
    publish, for scoring as vtolpose's is (every truth sample, the poses between fixes included)."""
    poses: list[tuple[int, Any, np.ndarray]] = []  # (time, gtsam Pose3, velocity)
    ends = [t for t, *_ in posteriors[1:]] + [int(t_imu[-1]) + 1]
    for (t_fix, pose, vel, bias), t_end in zip(posteriors, ends):
        poses.append((t_fix, pose, np.asarray(vel)))
        start, pim = gtsam.NavState(pose, vel), gtsam.PreintegratedCombinedMeasurements(params, bias)
        i = max(int(np.searchsorted(t_imu, t_fix, side="right")) - 1, 0)  # as the run: from the sample at or before
        while i + 1 < len(t_imu) and t_imu[i + 1] < t_end:
            pim.integrateMeasurement(accel[i], gyro[i], (t_imu[i + 1] - t_imu[i]) * 1e-9)
            i += 1
            nav = pim.predict(start, bias)
            poses.append((int(t_imu[i]), nav.pose(), nav.velocity()))
    return Trajectory(np.array([t for t, _, _ in poses], dtype=np.int64), np.array([p.translation() for _, p, _ in poses]),
                      np.array([v for _, _, v in poses]), rot_to_quat(np.array([p.rotation().matrix() for _, p, _ in poses])))


def bench_euroc_reference(echo: Callable[[str], None] = print) -> list[Row]:
    """Each EuRoC flight: vtolpose's IMU+GPS replay speed (both variants) and the reference's, same inputs, same run; then both sides' position scored alike."""
    try:
        gtsam = importlib.import_module("gtsam")
    except ImportError:
        gtsam = None
        echo("  euroc-reference: the GTSAM reference skipped: gtsam is not installed (pip install 'vtolpose[bench]')")
    flights = flights_or_skip("euroc-reference", echo)
    if not flights:
        return []
    load_compiled_kernels()  # once per process, before the first replay (not in its time)
    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as tmp:
        for flight in flights:
            dataset = imported_flight(flight, Path(tmp))
            walls: dict[str, list[float]] = {variant: [] for variant in VARIANTS}
            cpus: dict[str, list[float]] = {variant: [] for variant in VARIANTS}
            refs: list[dict[str, Any]] = []
            trajectories = {}
            for round_ in range(ROUNDS):  # the two sides in turn, so that a slow minute costs both
                for variant in VARIANTS:
                    cpu0 = time.process_time()
                    result = replay(dataset, load_config(None, {"estimator": {"variant": variant}}), ["imu", "gps"])
                    walls[variant].append(result.wall_s)
                    cpus[variant].append(time.process_time() - cpu0)
                    duration_s = result.duration_s
                    trajectories[variant] = result.trajectory  # the same every round: a replay is deterministic
                if gtsam is not None:
                    refs.append(reference_run(gtsam, dataset, causal=round_ == 0))
            rates = {variant: duration_s / min(walls[variant]) for variant in VARIANTS}
            cpu_rates = {variant: duration_s / min(cpus[variant]) for variant in VARIANTS}
            for variant in VARIANTS:
                rows.append(Row(f"{flight.name} replay imu,gps ({variant})", rates[variant], "x real time",
                                f"best of {ROUNDS} (median {duration_s / float(np.median(walls[variant])):.0f} x); "
                                f"{min(walls[variant]):.2f} s wall; {cpu_rates[variant]:.0f} x per CPU second",
                                REPLAY_TARGET))
            if not refs:
                continue
            ref_wall, ref_cpu = min(r["wall_s"] for r in refs), min(r["cpu_s"] for r in refs)
            ref_rate, ref_cpu_rate = refs[0]["duration_s"] / ref_wall, refs[0]["duration_s"] / ref_cpu
            rows.append(Row(f"{flight.name} GTSAM reference", ref_rate, "x real time",
                            f"best of {ROUNDS} (median {refs[0]['duration_s'] / float(np.median([r['wall_s'] for r in refs])):.0f} x); "
                            f"{ref_wall:.2f} s wall, {ref_cpu_rate:.0f} x per CPU second; preintegration + GPS, "
                            f"{LAG_S:g}-s fixed lag, given the truth's initial attitude; position RMSE {refs[0]['rmse_m']:.3f} m"))
            for variant in VARIANTS:  # per CPU second too: on a shared machine the wall clock carries others' load
                rows.append(Row(f"{flight.name} vtolpose / reference ({variant})", rates[variant] / ref_rate, "x",
                                f"real-time factors, each side's best of {ROUNDS}, same inputs, same run; "
                                f"{cpu_rates[variant] / ref_cpu_rate:.2f} x per CPU second", RATIO_TARGET))
            if dataset.truth() is not None:
                datasheet = sensor_white_noise(flight.source)
                extra = {"the IMU's datasheet": reference_run(gtsam, dataset, causal=True, white=datasheet)} if datasheet else {}
                rows += accuracy_rows(flight.name, dataset, trajectories, {"the vehicle file": refs[0], **extra})
    return rows


def sensor_white_noise(source: Path) -> tuple[float, float] | None:
    """The gyroscope's and accelerometer's white-noise densities of the recording's own ``imu0/sensor.yaml`` (the
    IMU's static datasheet figures, which the vehicle file raises for the rotors' vibration), None without one."""
    path = source / "mav0" / "imu0" / "sensor.yaml"
    if not path.is_file():
        return None
    try:
        doc = load_yaml_file(path)  # EuRoC's have OpenCV's header line
        return float(doc["gyroscope_noise_density"]), float(doc["accelerometer_noise_density"])
    except (CalibrationError, KeyError, TypeError, ValueError):
        return None


def accuracy_rows(flight: str, dataset: Dataset, trajectories: dict[str, Trajectory],
                  refs: dict[str, dict[str, Any]]) -> list[Row]:
    """Position ÷ the GPS's own error, both sides scored both ways: right after each fix's update only, as a
    smoother scores itself (:func:`at_fix_position_rmse`), and at every truth sample after the rigid alignment, as
    ``vtolpose bench --only euroc`` scores vtolpose (between fixes the pose is a prediction). ``refs``: reference
    runs (with ``trajectory``) by the IMU noise they were given."""
    gps_rmse = scored_gps_rmse(dataset)
    sides = {f"GTSAM reference ({noise}'s noise)": ref["trajectory"] for noise, ref in refs.items()}
    sides.update({f"vtolpose ({variant})": trajectory for variant, trajectory in trajectories.items()})
    rows: list[Row] = []
    for name, trajectory in sides.items():
        rows += [
            Row(f"{flight} {name}: position / GPS, at the fixes", at_fix_position_rmse(trajectory, dataset) / gps_rmse,
                "ratio", "the first pose at or after each fix, against the truth there, no alignment"),
            Row(f"{flight} {name}: position / GPS, every truth sample",
                scored_position_rmse(trajectory, dataset) / gps_rmse,
                "ratio", "as vtolpose bench --only euroc: the poses between fixes too, after the rigid alignment"),
        ]
    return rows
