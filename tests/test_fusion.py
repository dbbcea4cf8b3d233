"""Fusion order: the delayed horizon fuses in time order, late measurements at their own time, the
predictor reaches the newest sample; everything deterministic."""

import dataclasses

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from vtolpose.config import load_config
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.estimator.filter import Estimator
from vtolpose.estimator.fusion import FusionCore, FusionOptions, nominal_step
from vtolpose.estimator.inertial.imu_delta import ImuDownsampler
from vtolpose.estimator.core.measurements import GpsFix, ImuSample
from vtolpose.service.runtime.wiring import filter_options

from propagation_oracle import integrate_nominal

DELAY = 0.15


@pytest.fixture(scope="module")
def flight():
    return simulate_flight("landfill", 40.0, 5)


@pytest.fixture(scope="module")
def reference(flight):
    return in_order(flight)


def new_estimator(flight, cfg=None) -> Estimator:
    cfg = cfg or load_config()
    return Estimator(flight.calibration, filter_options(cfg, flight.calibration.imu.noise))


def imu_samples(flight) -> list[ImuSample]:
    imu = flight.imu
    return [ImuSample(int(t), g, a) for t, g, a in zip(imu.t_ns, imu.gyro, imu.accel)]


def gps_fixes(flight) -> list[GpsFix]:
    g = flight.gps
    return [GpsFix(int(t), p, float(h), float(v)) for t, p, h, v in zip(g.t_ns, g.p_ned, g.sigma_h, g.sigma_v)]


def in_order(flight, cfg=None):
    """The plain offline loop: every sample in time order (IMU first at equal times), state recorded when it
    advanced; a fix is given the next sample, as the fusion gives it (Estimator.imu_ahead)."""
    est = new_estimator(flight, cfg)
    events = sorted([(s.t_ns, 0, s) for s in imu_samples(flight)] + [(f.t_ns, 1, f) for f in gps_fixes(flight)],
                    key=lambda e: (e[0], e[1]))
    out, last = [], None
    for i, (_, kind, s) in enumerate(events):
        if kind == 0:
            if est.process_imu(s.t_ns, s.gyro, s.accel) and est.state is not None and (last is None or est.state.t_ns > last):
                last = est.state.t_ns
                out.append((last, est.state.p.copy(), est.state.q.copy()))
        else:
            after = next((x for _, k, x in events[i + 1:] if k == 0), None)
            est.imu_ahead((after.t_ns, after.gyro, after.accel) if after is not None else None)
            est.process_gps(s)
            est.imu_ahead(None)
    return est, out


def through_core(flight, delay_s=DELAY, gps_late_s=0.0, deliver_rest=True, **options):
    """Feed the core as a live system would: each fix arrives ``gps_late_s`` after its time."""
    fused = []
    core = FusionCore(new_estimator(flight), FusionOptions(delay_s=delay_s, **options),
                      on_fused=lambda pose: fused.append((pose.t_ns, pose.p.copy(), pose.q.copy())))
    fixes = gps_fixes(flight)
    k = 0
    for s in imu_samples(flight):
        while k < len(fixes) and fixes[k].t_ns + gps_late_s * 1e9 <= s.t_ns:
            fix = fixes[k]
            core.add_measurement(fix.t_ns, lambda est, f=fix: est.process_gps(f), "gps")
            k += 1
        core.add_imu(s)
    for fix in fixes[k:] if deliver_rest else ():  # arriving after the last IMU sample
        core.add_measurement(fix.t_ns, lambda est, f=fix: est.process_gps(f), "gps")
    return core, fused


def assert_same_trajectory(a, b):
    assert [t for t, _, _ in a] == [t for t, _, _ in b]
    assert np.array_equal(np.array([p for _, p, _ in a]), np.array([p for _, p, _ in b]))
    assert np.array_equal(np.array([q for _, _, q in a]), np.array([q for _, _, q in b]))


def test_delayed_fusion_gives_exactly_the_in_order_result(flight, reference):
    est, trajectory = reference
    core, fused = through_core(flight, gps_late_s=0.0)
    core.flush()
    assert_same_trajectory(fused, trajectory)
    assert core.counts["gps"].rejected == {}
    assert core.est.counts_report() == est.counts_report()


@pytest.mark.parametrize("variant, heading", [("thesis", "dataset"), ("biases", "dataset"), ("biases", "gps"),
                                              ("thesis", "gps")])
def test_runs_of_samples_fuse_exactly_as_one_at_a_time(flight, variant, heading):
    """Without a prediction to keep, the samples the horizon passes go to the estimator as runs
    (Estimator.process_imu_run: the steps' deltas, the rest detector's and the levelling's sums worked
    out for the whole run); trajectory, covariance and counts are bit for bit those of the sample-by-sample
    loop, also while the heading is searched for (heading hypotheses, levelling)."""
    cfg = load_config(None, {"estimator": {"variant": variant, "heading": {"source": heading}}})
    est, reference = in_order(flight, cfg)
    fused, accepted = [], []
    core = FusionCore(new_estimator(flight, cfg), FusionOptions(delay_s=DELAY, predict=False),
                      on_fused=lambda pose: fused.append((pose.t_ns, pose.p.copy(), pose.q.copy())))
    run = core.est.process_imu_run
    core.est.process_imu_run = lambda *args: accepted.append(run(*args)) or accepted[-1]
    fixes, k = gps_fixes(flight), 0
    for s in imu_samples(flight):
        while k < len(fixes) and fixes[k].t_ns <= s.t_ns:
            core.add_measurement(fixes[k].t_ns, lambda e, f=fixes[k]: e.process_gps(f), "gps")
            k += 1
        core.add_imu(s, fuse=False)
        if s.t_ns % 40_000_000 < 8_000_000:  # the horizon advanced now and then: runs of a few samples
            core.advance()
    core.flush()
    assert sum(accepted) > 100 and len(fused) > 1000
    assert est.counts["still"].used > 0  # the rest detector's chunks were judged inside runs too
    if heading == "gps":  # the heading was searched for, and levelled meanwhile
        assert est.counts["level"].used > 10 and est.heading_aligned
    assert_same_trajectory(fused, reference)
    assert np.array_equal(core.est.state.cov, est.state.cov)
    assert core.est.counts_report() == est.counts_report()


def pose_fields(pose) -> tuple:
    """Every field of a pose, arrays as copies (a later change to one would show)."""
    return tuple(np.array(value, copy=True) if isinstance(value, np.ndarray) else value
                 for value in (getattr(pose, f.name) for f in dataclasses.fields(pose)))


def feed_in_batches(core: FusionCore, flight, size: int = 12) -> None:
    """The flight's IMU samples in batches of ``size``, each GPS fix queued before the batch that passes it; flushed."""
    fixes, k = gps_fixes(flight), 0
    samples = imu_samples(flight)
    for start in range(0, len(samples), size):
        batch = samples[start:start + size]
        while k < len(fixes) and fixes[k].t_ns <= batch[0].t_ns:
            core.add_measurement(fixes[k].t_ns, lambda est, f=fixes[k]: est.process_gps(f), "gps")
            k += 1
        add_batch(core, batch)
    core.flush()


def add_batch(core: FusionCore, batch: list) -> None:
    """IMU samples (a list of ImuSample) as one batch of arrays."""
    core.add_imu_batch(np.array([s.t_ns for s in batch]), np.array([s.gyro for s in batch]),
                       np.array([s.accel for s in batch]))


def feed_batch(core: FusionCore, batch: list, batched: bool) -> None:
    """IMU samples as one batch of arrays (``batched``) or one by one."""
    if batched:
        add_batch(core, batch)
    else:
        for sample in batch:
            core.add_imu(sample)


def flushed(core: FusionCore, fused: list) -> tuple:
    """The core flushed: its fused poses, its counts and its estimator's."""
    core.flush()
    return fused, core.counts_report(), core.est.counts_report()


def recording_core(flight) -> tuple[FusionCore, list]:
    """A core without a prediction, and the list it appends each fused pose's time, position and attitude to."""
    fused: list = []
    core = FusionCore(new_estimator(flight), FusionOptions(delay_s=DELAY, predict=False),
                      on_fused=lambda pose: fused.append((pose.t_ns, pose.p.copy(), pose.q.copy())))
    return core, fused


def fused_pose_fields(flight, cfg, runs: bool) -> tuple[list[tuple], int]:
    """Every field of every fused pose, fed in batches of 12 samples: sample by sample (a prediction kept: no
    runs) or as runs with their poses as :class:`FusedRun` (``on_fused_run``); and how many came in runs."""
    made, in_runs = [], []

    def take_run(run):
        in_runs.append(len(run))
        made.extend(pose_fields(pose) for pose in run.poses())
    core = FusionCore(new_estimator(flight, cfg), FusionOptions(delay_s=DELAY, predict=not runs),
                      on_fused=lambda pose: made.append(pose_fields(pose)), on_fused_run=take_run if runs else None)
    feed_in_batches(core, flight)
    return made, sum(in_runs)


@pytest.mark.parametrize("variant, heading", [("biases", "gps"), ("thesis", "gps"), ("biases", "dataset")])
def test_the_poses_of_a_fused_run_are_those_made_step_by_step(flight, variant, heading):
    """A run's compiled steps hand their poses over at once (FusedRun: covariances, rate variances and quality
    caps worked out for all of them); every field of every pose is the one the steps one by one make, while
    the heading is searched for (its published variance that of an unknown heading) and once it is known."""
    cfg = load_config(None, {"estimator": {"variant": variant, "heading": {"source": heading}}})
    one_by_one, _ = fused_pose_fields(flight, cfg, runs=False)
    in_runs, from_runs = fused_pose_fields(flight, cfg, runs=True)
    assert from_runs > len(in_runs) // 2 and len(in_runs) == len(one_by_one) > 1000
    for now, was in zip(in_runs, one_by_one):
        for a, b in zip(now, was):
            assert type(a) is type(b) and np.array_equal(a, b), now[0]


def test_a_fused_run_never_changes_after_it_was_made(flight):
    """A FusedRun works out its published covariances when asked: asked at the end of the flight, after the
    updates that followed it changed the filter's covariance in place, it says what it said when it was made."""
    made = []
    core = FusionCore(new_estimator(flight), FusionOptions(delay_s=DELAY, predict=False),
                      on_fused_run=lambda run: made.append((run, [pose_fields(pose) for pose in run.poses()])))
    fixes, k = gps_fixes(flight), 0
    for s in imu_samples(flight):
        while k < len(fixes) and fixes[k].t_ns <= s.t_ns:
            core.add_measurement(fixes[k].t_ns, lambda est, f=fixes[k]: est.process_gps(f), "gps")
            k += 1
        core.add_imu(s, fuse=False)
        if s.t_ns % 40_000_000 < 8_000_000:
            core.advance()
    core.flush()
    assert sum(len(run) for run, _ in made) > 1000 and core.est.counts["gps"].used > 100
    for run, then in made:
        for now, was in zip(run.poses(), then):
            for a, b in zip(pose_fields(now), was):
                assert np.array_equal(a, b), now.t_ns


@pytest.mark.parametrize("predict, heading", [(True, "gps"), (False, "gps"), (False, "dataset")])
def test_a_fused_pose_never_changes_after_it_was_made(flight, predict, heading):
    """A fused pose holds the state's own nominal arrays (no copies: the filter replaces them, never changes
    them in place). Whatever the filter does afterwards — steps one by one or as runs, GPS updates, the
    heading search and its placement, rest updates — every pose still says what it said when it was made."""
    cfg = load_config(None, {"estimator": {"heading": {"source": heading}}})
    made = []
    core = FusionCore(new_estimator(flight, cfg), FusionOptions(delay_s=DELAY, predict=predict),
                      on_fused=lambda pose: made.append((pose, pose_fields(pose))))
    feed_in_batches(core, flight)
    est = core.est
    assert len(made) > 1000 and est.counts["gps"].used > 100 and est.counts["still"].used > 0
    if heading == "gps":
        assert est.heading_aligned and est.heading_placement is not None
    for pose, then in made:
        for now, was in zip(pose_fields(pose), then):
            assert np.array_equal(now, was), pose.t_ns


@pytest.mark.parametrize("late_s", [0.1, 0.2])
def test_held_runs_change_neither_the_result_nor_what_is_too_late(flight, late_s):
    """Without a prediction, a run that would end at the horizon waits to be fused with the next stretch
    (half as many runs). Fed in batches, the core gives the poses and counts of the sample-by-sample core,
    fixes that arrive after the horizon passed them (0.2 s late) refused as too late all the same."""
    fixes, samples = gps_fixes(flight), imu_samples(flight)
    results, held = [], []
    for batched in (False, True):
        core, fused = recording_core(flight)
        k = 0
        for start in range(0, len(samples), 12):
            batch = samples[start:start + 12]
            while k < len(fixes) and fixes[k].t_ns + late_s * 1e9 <= batch[0].t_ns:
                core.add_measurement(fixes[k].t_ns, lambda est, f=fixes[k]: est.process_gps(f), "gps")
                k += 1
            feed_batch(core, batch, batched)
            if batched:
                held.append(core.fused_until_ns is not None and core.est.state is not None
                            and core.fused_until_ns > core.est.state.t_ns)  # passed by the horizon, not yet fused
        results.append(flushed(core, fused))
    (fused_one, *counts_one), (fused_batched, *counts_batched) = results
    assert sum(held) > 100  # runs were held
    assert_same_trajectory(fused_batched, fused_one)
    assert counts_batched == counts_one
    gps = counts_one[0]["gps"]  # the same in both, too-late refusals included
    assert gps["rejected"]["too_late"] > 100 and (gps["used"] > 200 if late_s < DELAY else gps["used"] == 0)


def test_late_measurements_are_fused_at_their_own_time(flight, reference):
    """Fixes arriving 100 ms late, within the 150 ms horizon, change nothing at all."""
    core, fused = through_core(flight, gps_late_s=0.1)
    core.flush()
    assert_same_trajectory(fused, reference[1])


def test_measurements_older_than_the_horizon_are_counted_not_fused(flight):
    core, _ = through_core(flight, gps_late_s=0.3, deliver_rest=False)
    n = len(flight.gps.t_ns)
    arrived = sum(1 for t in flight.gps.t_ns if t + 0.3e9 <= flight.imu.t_ns[-1])
    assert core.counts["gps"].received == arrived and arrived > n - 5
    assert core.counts["gps"].rejected == {"too_late": arrived}
    assert core.est.counts["gps"].received == 0


def test_measurements_are_applied_in_time_order_at_their_time(flight):
    """Each measurement meets the filter exactly at its time: every IMU sample up to it (IMU first at equal
    times) consumed, none after it. A measurement fused one sample early or late changes the count."""
    core = FusionCore(new_estimator(flight), FusionOptions(delay_s=DELAY))
    samples = imu_samples(flight)
    applied = []
    for s in samples[:2000]:
        core.add_imu(s)
    t_a, t_b = samples[1995].t_ns - 40_000_000, samples[1995].t_ns - 80_000_000  # inside the horizon
    t_c = samples[1980].t_ns + 3_000_000  # between two samples
    sample_times = {s.t_ns for s in samples}
    assert t_a in sample_times and t_b in sample_times and t_c not in sample_times
    for name, t in (("a", t_a), ("b", t_b), ("c", t_c)):
        core.add_measurement(t, lambda est, name=name: applied.append((name, est.counts["imu"].received)), "test")
    for s in samples[2000:2100]:
        core.add_imu(s)
    assert [name for name, _ in applied] == ["c", "b", "a"]
    consumed_by = {name: sum(s.t_ns <= t for s in samples) for name, t in (("a", t_a), ("b", t_b), ("c", t_c))}
    assert dict(applied) == consumed_by
    assert core.counts["test"].used == 3


def test_at_equal_times_gps_fuses_before_camera_whichever_arrived_first(flight):
    """A full-speed replay hands frames over early, so a frame's features may queue before the fix of the same
    time stamp; the fusion order must not depend on that (the streams' order: GPS, then camera, then others)."""
    core = FusionCore(new_estimator(flight), FusionOptions(delay_s=DELAY))
    samples = imu_samples(flight)
    for s in samples[:2000]:
        core.add_imu(s)
    t = samples[1995].t_ns
    applied = []
    for kind in ("other", "camera", "gps"):
        core.add_measurement(t, lambda est, kind=kind: applied.append(kind), kind)
    for s in samples[2000:2100]:
        core.add_imu(s)
    assert applied == ["gps", "camera", "other"]


def test_prediction_reaches_the_newest_sample_by_nominal_propagation(flight):
    core = FusionCore(new_estimator(flight), FusionOptions(delay_s=DELAY))
    samples = imu_samples(flight)[:3000]
    for s in samples:
        core.add_imu(s)
    pose = core.output()
    state = core.est.state
    assert pose.t_ns == samples[-1].t_ns and state.t_ns < pose.t_ns - 0.1e9
    # Independent re-propagation: one-sample deltas and integrate_nominal from the delayed state.
    later = [s for s in samples if s.t_ns > state.t_ns]
    before = max((s for s in samples if s.t_ns <= state.t_ns), key=lambda s: s.t_ns)
    ds = ImuDownsampler(1e12)
    ds.add(state.t_ns, before.gyro, before.accel)
    p, v, q = state.p, state.v, state.q
    for s in later:
        d = ds.add(s.t_ns, s.gyro, s.accel)
        p, v, q, _ = integrate_nominal(p, v, q, state.b_g, state.b_a, d.dtheta, d.dvel, d.dt, core.est.propagator.gravity)
    assert np.allclose(pose.p, p, atol=1e-9) and np.allclose(pose.v, v, atol=1e-9) and np.allclose(pose.q, q, atol=1e-12)
    # The prediction's covariance: symmetric, positive definite, attitude grown by the gyro noise.
    cov = pose.pose_cov
    assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
    assert np.all(np.diag(cov)[3:] > np.diag(state.pose_covariance())[3:])


def continuous_growth(P0: np.ndarray, horizon_s: float, f_w: np.ndarray, accel_var_w: np.ndarray,
                      gyro_var_w: np.ndarray) -> np.ndarray:
    """[δp, δv, δθ] covariance after ``horizon_s`` of the continuous error model at a constant world
    specific force ``f_w``: δp' = δv, δv' = -[f_w]x δθ + w_a, δθ' = w_g (white noise of the given
    world-frame spectral densities), discretised exactly by Van Loan's matrix exponential."""
    A = np.zeros((9, 9))
    A[0:3, 3:6] = np.eye(3)
    fx, fy, fz = f_w
    A[3:6, 6:9] = -np.array([[0.0, -fz, fy], [fz, 0.0, -fx], [-fy, fx, 0.0]])
    Qc = np.zeros((9, 9))
    Qc[3:6, 3:6], Qc[6:9, 6:9] = accel_var_w, gyro_var_w
    M = np.zeros((18, 18))
    M[:9, :9], M[:9, 9:], M[9:, 9:] = -A, Qc, A.T
    E = expm(M * horizon_s)
    Phi = E[9:, 9:].T
    return Phi @ P0 @ Phi.T + Phi @ E[:9, 9:]


def test_prediction_covariance_grows_with_the_horizon_as_the_error_model_says(flight):
    """At rest (the flight's first 10 s) the predicted pose's [δp, δv, δθ] covariance is the delayed one
    grown over the prediction horizon by the continuous error model, for short and long horizons alike."""
    samples = imu_samples(flight)
    t_end = samples[0].t_ns + 8_000_000_000  # the filter started at ~3 s; still at rest
    gravity = flight.calibration.imu.gravity
    r_true = Rotation.from_quat(flight.truth.q[0][[1, 2, 3, 0]]).as_matrix()  # attitude on the pad
    growth_of_position = []
    for delay_s in (0.05, 0.2, 0.6):
        core = FusionCore(new_estimator(flight), FusionOptions(delay_s=delay_s))
        for s in samples:
            if s.t_ns > t_end:
                break
            core.add_imu(s)
        pose, state, noise = core.output(), core.est.state, core.est.noise
        horizon_s = (pose.t_ns - state.t_ns) * 1e-9
        assert pose.fused_t_ns == state.t_ns and abs(horizon_s - delay_s) < 0.02
        P0 = state.cov[:9, :9]
        expected = continuous_growth(P0, horizon_s, np.array([0.0, 0.0, -gravity]),  # at rest: f = -g
                                     r_true @ np.diag(noise.accel_noise_density**2) @ r_true.T,
                                     r_true @ np.diag(noise.gyro_noise_density**2) @ r_true.T)
        for rows in (slice(0, 3), slice(3, 6), slice(6, 9)):
            for cols in (slice(0, 3), slice(3, 6), slice(6, 9)):
                want, got = expected[rows, cols] - P0[rows, cols], pose.cov9[rows, cols] - P0[rows, cols]
                scale = np.abs(want).max()
                assert scale > 0.0 and np.abs(got - want).max() < 0.02 * scale, (delay_s, rows, cols)
        growth_of_position.append(np.trace(pose.cov9[0:3, 0:3] - P0[0:3, 0:3]))
    assert growth_of_position[0] > 0.0 and np.all(np.diff(growth_of_position) > 0.0)


def test_the_published_pose_is_capped_while_the_gps_is_stale(flight):
    """The pose that leaves (the prediction, not the fused state) follows the documented health rule:
    quality ceiling 100 while GPS fixes are being used, ``stale_quality_cap`` once none was used for
    ``gps_stale_s`` (config/default.yaml, estimator/health.py), judged at the filter's time."""
    cfg = load_config()
    stale_ns, stale_cap = cfg["estimator.health.gps_stale_s"] * 1e9, cfg["estimator.health.stale_quality_cap"]
    assert stale_cap < 100
    core = FusionCore(new_estimator(flight), FusionOptions(delay_s=DELAY))
    t0 = flight.imu.t_ns[0]
    fixes = [f for f in gps_fixes(flight) if f.t_ns < t0 + 25e9]  # the receiver goes quiet at 25 s
    used_at: list[int] = []

    def fuse(est, fix):
        outcome = est.process_gps(fix)
        if outcome is not None and outcome.accepted:
            used_at.append(fix.t_ns)

    caps, k = [], 0
    for s in imu_samples(flight):
        while k < len(fixes) and fixes[k].t_ns <= s.t_ns:
            core.add_measurement(fixes[k].t_ns, lambda est, f=fixes[k]: fuse(est, f), "gps")
            k += 1
        core.add_imu(s)
        pose = core.output()
        if pose is not None and pose.position_initialized:
            caps.append((pose.fused_t_ns, pose.quality_cap))
    assert core.est.reset_counter == 0 and len(used_at) > 150
    used = np.array(used_at)
    in_use, stale = [], []
    for t, cap in caps:
        since_used = t - used[np.searchsorted(used, t, side="right") - 1]
        if since_used < stale_ns - 50_000_000:
            in_use.append(cap)
        elif since_used > stale_ns + 50_000_000:
            stale.append(cap)
    assert len(in_use) > 1000 and set(in_use) == {100}
    assert len(stale) > 1000 and set(stale) == {stale_cap}


def test_publishing_first_fuses_nothing_until_advance(flight):
    core = FusionCore(new_estimator(flight), FusionOptions(delay_s=DELAY))
    samples = imu_samples(flight)
    for s in samples[:1500]:
        core.add_imu(s)
    fused_until = core.fused_until_ns
    core.add_imu(samples[1500], fuse=False)
    assert core.output().t_ns == samples[1500].t_ns and core.fused_until_ns == fused_until
    core.advance()
    assert core.fused_until_ns > fused_until


def test_buffer_limits_are_counted(flight):
    core = FusionCore(new_estimator(flight), FusionOptions(delay_s=1.0, max_pending=2, max_imu_buffer=50))
    samples = imu_samples(flight)
    for s in samples[:200]:
        core.add_imu(s)
    assert core.buffered_imu == 50 and core.counts["imu"].flagged["horizon_forced"] > 0
    t = samples[199].t_ns
    assert [core.add_measurement(t, lambda est: None, "x") for _ in range(3)] == [True, True, False]
    assert core.counts["x"].rejected == {"buffer_full": 1}
    assert not core.add_imu(samples[10])  # older than the newest sample
    assert core.counts["imu"].rejected == {"time_not_increasing": 1}


def test_nominal_step_is_integrate_nominal_on_a_one_sample_delta():
    rng = np.random.default_rng(3)
    for _ in range(20):
        p, v = rng.normal(size=3), rng.normal(size=3)
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        b_g, b_a = rng.normal(scale=0.01, size=3), rng.normal(scale=0.1, size=3)
        g0, g1, a0, a1 = rng.normal(size=3), rng.normal(size=3), rng.normal(size=3) * 5, rng.normal(size=3) * 5
        dt = 0.008
        ds = ImuDownsampler(1e12)
        ds.add(0, g0, a0)
        d = ds.add(8_000_000, g1, a1)
        ref = integrate_nominal(p, v, q, b_g, b_a, d.dtheta, d.dvel, d.dt, np.array([0.0, 0.0, 9.81]))
        got = nominal_step(tuple(p), tuple(v), tuple(q), tuple(b_g), tuple(b_a), tuple(g0), tuple(a0), tuple(g1),
                           tuple(a1), dt, 9.81)
        for a, b in zip(got, ref[:3]):
            assert np.allclose(a, b, atol=1e-13)


def test_the_batches_kept_for_slicing_are_those_with_samples_queued(flight):
    """A run within one batch is a slice of its arrays; a batch is kept only while samples of it wait to be fused,
    also while none are fused in runs (a filter not started yet): the list stays as short as the queue."""
    core = FusionCore(new_estimator(flight), FusionOptions(delay_s=DELAY, predict=False))
    imu = flight.imu
    longest, oldest = 0, None
    for start in range(0, 4000, 10):
        core.add_imu_batch(imu.t_ns[start:start + 10], imu.gyro[start:start + 10], imu.accel[start:start + 10])
        longest = max(longest, len(core._batches))
        # What was fused before this batch came leaves with it.
        assert oldest is None or all(t[-1] >= oldest for t, _, _ in core._batches)
        oldest = core._queue[0][0] if core._queue else None
    assert core.est.state is not None
    assert longest <= int(DELAY * 200 / 10) + 3  # the horizon's lag in batches, and one being fused


def test_a_batch_out_of_order_within_is_taken_sample_by_sample(flight):
    """A batch whose times repeat or step back inside it goes through the per-sample rules, as if its samples came
    one by one: the same poses, the same refusals."""
    samples = imu_samples(flight)[:3000]
    batches = [samples[start:start + 12] for start in range(0, len(samples), 12)]
    batches[100] = batches[100][:5] + [batches[100][4]] + batches[100][5:]  # a time repeated
    b = batches[200]
    batches[200] = b[:3] + [b[4], b[3]] + b[5:]  # two swapped
    results = []
    for batched in (False, True):
        core, fused = recording_core(flight)
        for batch in batches:
            feed_batch(core, batch, batched)
        results.append(flushed(core, fused))
    (fused_one, *counts_one), (fused_batched, *counts_batched) = results
    assert counts_batched == counts_one
    assert sum(counts_one[0]["imu"]["rejected"].values()) == 2  # the repeated time and the one stepping back
    assert_same_trajectory(fused_batched, fused_one)
