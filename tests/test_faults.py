"""Faults played on a replay: what the estimate does, what the published quality says, how fast it
comes back. These pin the README's fault table on a short landfill IMU+GPS flight (GPS σ 2 m),
each faulty run against the same flight without the fault.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.estimator.core.measurements import CameraFrame, GpsFix, ImuSample
from vtolpose.service.bench.faults import FaultRun, recovery_time_s, traced_replay, trajectory_deviation_m, window_nees
from vtolpose.service.cli import main
from vtolpose.service.replay.faults import FaultError, FaultInjector, parse_fault, parse_faults

DURATION_S = 70.0
STALE_CAP, RESET_CAP = 50, 20  # estimator.health defaults: quality ceilings while stale / after a reset


@pytest.fixture(scope="module")
def landfill(tmp_path_factory) -> Dataset:
    root = tmp_path_factory.mktemp("faults") / "landfill"
    write_flight(simulate_flight("landfill", DURATION_S, 3), root)
    return Dataset.open(root)


@pytest.fixture(scope="module")
def clean(landfill) -> FaultRun:
    return traced_replay(landfill, load_config(), ["imu", "gps"])


def faulty(landfill: Dataset, *faults: str, seed: int = 0) -> FaultRun:
    run = traced_replay(landfill, load_config(), ["imu", "gps"], list(faults), seed=seed)
    assert np.all(np.isfinite(np.array(run.trace.p))) and np.all(np.isfinite(np.array(run.trace.q)))
    return run


def counts(run: FaultRun, sensor: str) -> dict:
    return run.result.estimator.counts_report()[sensor]


# ------------------------------------------------------------------------------- specs


@pytest.mark.parametrize("spec, expected", [
    ("gps-off:60:30", dict(kind="gps-off", sensor="gps", start_s=60.0, duration_s=30.0)),
    ("camera-off:5:2.5", dict(kind="camera-off", sensor="camera", start_s=5.0, duration_s=2.5)),
    ("imu-gap:40:0.5", dict(kind="imu-gap", sensor="imu", duration_s=0.5)),
    ("gps-jump:40:20,0,0", dict(offset_m=(20.0, 0.0, 0.0), duration_s=1.0)),
    ("gps-jump:40:0,-5,1:10", dict(offset_m=(0.0, -5.0, 1.0), duration_s=10.0)),
    ("gps-multipath:30:30:10:0.3", dict(sigma_m=10.0, rate=0.3)),
    ("camera-freeze:12:3", dict(kind="camera-freeze", sensor="camera")),
    ("clock-step:45:+2.0", dict(sensor=None, step_s=2.0, duration_s=math.inf)),
    ("nan:imu:45:0.5", dict(sensor="imu", duration_s=0.5)),
])
def test_fault_specs_parse(spec, expected):
    fault = parse_fault(spec)
    for key, value in expected.items():
        assert getattr(fault, key) == value, key


@pytest.mark.parametrize("spec, message", [
    ("", "empty"),
    ("gps-of:1:2", "unknown kind 'gps-of'"),
    ("gps-off:10", "gps-off takes gps-off:START:DURATION"),
    ("gps-off:-1:5", "START '-1' must be >= 0"),
    ("gps-off:1:0", "DURATION '0' must be greater than 0"),
    ("gps-off:x:5", "START 'x' is not a number"),
    ("gps-off:nan:5", "must be finite"),
    ("gps-jump:1:20,0", "DN,DE,DD '20,0' must be three numbers"),
    ("gps-multipath:1:2:10:1.5", "RATE '1.5' must be a fraction"),
    ("clock-step:10:0", "STEP '0' must be non-zero"),
    ("nan:camera:1:1", "use camera-off or camera-freeze"),
])
def test_bad_fault_specs_name_the_part_at_fault(spec, message):
    with pytest.raises(FaultError, match="--fault") as err:
        parse_fault(spec)
    assert message in str(err.value)


def test_only_one_clock_step_per_replay():
    with pytest.raises(FaultError, match="at most one clock-step"):
        parse_faults(["clock-step:1:1", "clock-step:2:-1"])


# ------------------------------------------------------------------------------- injector


def stream(seconds: float = 4.0) -> list:
    """IMU at 100 Hz, GPS at 10 Hz, camera at 5 Hz (distinct images), in time order from t = 1 s."""
    t0 = 1_000_000_000
    out = []
    for k in range(int(seconds * 100)):
        t = t0 + k * 10_000_000
        out.append(ImuSample(t, np.full(3, 0.1), np.array([0.0, 0.0, -9.8])))
        if k % 10 == 0:
            out.append(GpsFix(t, np.array([float(k), 0.0, 0.0]), 1.0, 2.0))
        if k % 20 == 0:
            out.append(CameraFrame(t, np.full((4, 4), k % 256, np.uint8), k // 20))
    return out


def play(specs: list[str], seed: int = 0) -> tuple[list, FaultInjector]:
    injector = FaultInjector(parse_faults(specs), seed)
    played = [injector.apply(s) for s in stream()]
    return [s for s in played if s is not None], injector


def test_losses_drop_exactly_the_window():
    out, inj = play(["gps-off:1:1", "imu-gap:2:0.5", "camera-off:0:1"])
    gps = [s.t_ns for s in out if isinstance(s, GpsFix)]
    imu = [s.t_ns for s in out if isinstance(s, ImuSample)]
    assert len(gps) == 40 - 10 and not any(2.0e9 <= t < 3.0e9 for t in gps)
    assert len(imu) == 400 - 50 and not any(3.0e9 <= t < 3.5e9 for t in imu)
    assert [r["samples_affected"] for r in inj.report()] == [10, 50, 5]


def test_jump_multipath_freeze_nan_and_clock_step_change_only_their_window():
    original = {(type(s).__name__, s.t_ns): s for s in stream()}
    out, inj = play(["gps-jump:1:20,0,-3", "camera-freeze:2:1", "nan:imu:3:0.1", "clock-step:3.5:+2"])
    for s in out:
        data_t = s.t_ns - 2_000_000_000 if s.t_ns >= 6_500_000_000 else s.t_ns  # the stream ends at 5 s
        t_s = (data_t - 1_000_000_000) * 1e-9
        src = original[(type(s).__name__, data_t)]
        if isinstance(s, GpsFix):
            shift = [20.0, 0.0, -3.0] if 1.0 <= t_s < 2.0 else [0.0, 0.0, 0.0]
            assert np.allclose(s.p_ned - src.p_ned, shift)
        elif isinstance(s, CameraFrame):
            frozen = 2.0 <= t_s < 3.0
            assert np.array_equal(s.image, np.full((4, 4), 180) if frozen else src.image)  # the frame at 1.8 s repeats
        else:
            assert np.isnan(s.gyro).all() == (3.0 <= t_s < 3.1)
    assert [r["samples_affected"] for r in inj.report()] == [10, 5, 10, 50 + 5 + 2]
    stamps = np.array([s.t_ns for s in out])
    assert np.all(np.diff(inj.source_time_ns(stamps[stamps < 4.5e9])) >= 0)
    assert inj.source_time_ns(np.array([6_600_000_000]))[0] == 4_600_000_000


def test_multipath_is_reproducible_from_its_seed():
    def hits(seed: int) -> list[int]:
        out, _ = play(["gps-multipath:0:4:10:0.5"], seed)
        return [s.t_ns for s in out if isinstance(s, GpsFix) and s.p_ned[1] != 0.0]

    assert hits(1) == hits(1) != hits(2)
    assert 10 <= len(hits(1)) <= 30  # about half of the 40 fixes


# ------------------------------------------------------------------------------- replays


def test_gps_jump_is_rejected_counted_and_does_not_move_the_estimate(landfill):
    jump = faulty(landfill, "gps-jump:40:20,0,0")
    missing = faulty(landfill, "gps-off:40:1")
    assert jump.result.faults.report()[0]["samples_affected"] == 10
    gated = [counts(run, "gps")["rejected"]["chi2_gate"] for run in (jump, missing)]
    assert gated[0] - gated[1] == 10  # every jumped fix, beyond what the other fixes had anyway
    assert trajectory_deviation_m(jump, missing, landfill.gps().t_ns) < 0.01  # as if the fixes never came
    assert jump.resets[-1] == 0
    assert STALE_CAP <= jump.quality[jump.between(40, 45)].min() < 100  # stale for a moment, no reset


def test_persistent_gps_disagreement_resets_to_the_gps(landfill, clean):
    """15 s of fixes 20 m off: rejected until gps_reset_after_s, then the estimate, not the GPS, is
    taken to be wrong (a reset to it); when the fixes come back, the same again."""
    run = faulty(landfill, "gps-jump:30:20,0,0:15")
    assert run.result.estimator.health.reset_counts == {"gps_rejected": 2}
    assert run.error_m[run.between(40, 45)].min() > 15.0  # following the jumped GPS
    assert run.quality[run.between(35, 60)].min() == RESET_CAP
    assert recovery_time_s(run, 45.0, 2.0 * clean.rmse(20.0)) <= 10.0


def test_gps_loss_widens_the_covariance_honestly_then_recovers(landfill, clean):
    run = faulty(landfill, "gps-off:30:20")
    sigma = np.sqrt(run.result.covariances.cov[:, 0, 0])
    t_cov = (run.result.covariances.t_ns - landfill.imu().t_ns[0]) * 1e-9
    assert sigma[(t_cov > 49) & (t_cov < 50)].min() > 5 * sigma[(t_cov > 25) & (t_cov < 30)].max()
    assert window_nees(run, landfill, 30.0, 50.0)["fraction_in_band"] > 0.9
    assert run.quality[run.between(31.5, 50)].max() <= STALE_CAP
    assert run.resets[-1] == 0
    assert recovery_time_s(run, 50.0, 2.0 * clean.rmse(20.0)) <= 10.0
    assert np.median(run.quality[run.between(60, 62)]) > STALE_CAP


def test_short_imu_gap_is_bridged_long_one_resets(landfill, clean):
    short = faulty(landfill, "imu-gap:40:0.5")
    assert counts(short, "imu")["flagged"] == {"gap_bridged": 1} and short.resets[-1] == 0
    assert short.error_m[short.between(40, 50)].max() < 2.0
    long = faulty(landfill, "imu-gap:40:2")
    assert long.result.estimator.health.reset_counts == {"imu_gap": 1}
    assert long.quality[long.between(42, 43)].max() <= RESET_CAP
    assert long.error_m[long.between(40, 50)].max() < 5.0
    assert recovery_time_s(long, 42.0, 2.0 * clean.rmse(20.0)) <= 10.0


@pytest.mark.parametrize("step", ["+2.0", "-2.0"])
def test_clock_step_resets_and_recovers(landfill, clean, step):
    run = faulty(landfill, f"clock-step:40:{step}")
    assert run.result.estimator.health.reset_counts == {"imu_gap": 1}
    if step.startswith("-"):  # two seconds of samples stamped in the past: refused, counted
        late = run.result.fusion_counts["imu"]["rejected"]["time_not_increasing"]
        assert 2 * 125 - 5 <= late <= 2 * 125 + 5
    assert run.error_m[run.between(40, 50)].max() < 5.0
    assert recovery_time_s(run, 42.0, 2.0 * clean.rmse(20.0)) <= 12.0


def test_nan_bursts_are_counted_and_skipped(landfill):
    imu = faulty(landfill, "nan:imu:40:0.5")
    hit = imu.result.faults.report()[0]["samples_affected"]
    assert hit == 63 and counts(imu, "imu")["rejected"] == {"non_finite": hit}
    assert imu.resets[-1] == 0
    gps = faulty(landfill, "nan:gps:40:5")
    assert counts(gps, "gps")["rejected"]["non_finite"] == 50 and gps.resets[-1] == 0


def test_multipath_outliers_are_gated(landfill, clean):
    run = faulty(landfill, "gps-multipath:30:30:10:0.3", seed=1)
    extra = counts(run, "gps")["rejected"]["chi2_gate"] - counts(clean, "gps")["rejected"]["chi2_gate"]
    assert extra >= 0.6 * run.result.faults.report()[0]["samples_affected"]
    assert run.error_m[run.between(30, 60)].max() < 2.0 * clean.error_m[clean.between(30, 60)].max()
    assert run.resets[-1] == 0


def test_replay_command_plays_faults_into_the_report(landfill, tmp_path, capsys):
    report = tmp_path / "r.json"
    code = main(["replay", str(landfill.root), "--sensors", "imu,gps", "--no-progress", "--report", str(report),
                 "--fault", "gps-jump:40:20,0,0", "--fault", "nan:gps:50:1"])
    assert code == 0
    doc = json.loads(report.read_text())
    assert [f["samples_affected"] for f in doc["faults"]] == [10, 10]
    assert doc["health"]["resets"] == {} and "sensors" in doc["health"]
    assert main(["replay", str(landfill.root), "--fault", "gps-off:1"]) == 1
    assert "gps-off takes gps-off:START:DURATION" in capsys.readouterr().err
    assert main(["run", "--fault", "gps-off:1:1", "--duration", "1"]) == 2
    assert "use it with --replay" in capsys.readouterr().err


# ------------------------------------------------------------------------------- camera


@pytest.fixture(scope="module")
def book(rendered_book_dir) -> Dataset:
    return Dataset.open(rendered_book_dir)  # the 24 s rendered book flight (conftest.py)


def camera_run(book: Dataset, *faults: str) -> FaultRun:
    cfg = load_config(None, {"features": {"detector": "orb"}})
    return traced_replay(book, cfg, ["imu", "camera", "gps"], list(faults))


def test_camera_loss_and_frozen_frames_are_reported_and_stay_honest(book):
    clean = camera_run(book)
    dark = camera_run(book, "camera-off:12:6")
    assert dark.quality[dark.between(13.5, 18.0)].max() <= STALE_CAP < np.median(clean.quality[clean.between(13.5, 18)])
    assert np.median(dark.quality[dark.between(20, 22)]) > STALE_CAP  # frames back: no longer capped
    n, before = window_nees(dark, book, 12.0, 18.0), window_nees(clean, book, 12.0, 18.0)
    assert n["fraction_in_band"] >= 0.95  # every pose's NEES inside its 95 % band, as without the fault
    assert n["mean"] < 1.25 * before["mean"]
    assert dark.resets[-1] == 0
    frozen = camera_run(book, "camera-freeze:12:3")
    repeated = frozen.result.faults.report()[0]["samples_affected"]
    assert counts(frozen, "camera")["rejected"]["duplicate"] == repeated  # each repeats the frame before the window
    assert frozen.quality[frozen.between(13.5, 15.0)].max() <= STALE_CAP
    missing = camera_run(book, "camera-off:12:3")  # a frozen camera must cost no more than a dark one
    assert trajectory_deviation_m(frozen, missing, book.gps().t_ns) < 0.002
