"""Filter health (estimator.health) and the isolation of everything around the estimator: a broken
state is caught and rebuilt, stale sensors cap the published quality, and an output, a source or
a sample that raises is counted and logged once — the service carries on."""

from __future__ import annotations

import asyncio
import dataclasses
import logging

import numpy as np
import pytest

from vtolpose.config import load_config
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.estimator.filter import Estimator
from vtolpose.estimator.fusion import FusionOptions
from vtolpose.estimator.health import (
    FrameInnovations,
    GapWidener,
    HealthMonitor,
    HealthOptions,
    camera_verdict,
    gap_variances,
    state_problem,
)
from vtolpose.estimator.core.measurements import GpsFix, ImuSample
from vtolpose.estimator.core.state import FilterState, StateLayout
from vtolpose.service.runtime.loop import Runtime, RuntimeOptions
from vtolpose.service.runtime.status import FailureBook, pose_quality
from vtolpose.service.runtime.wiring import filter_options

from runtime_helpers import PoseList, flight_samples

S = 1_000_000_000


def sound_state() -> FilterState:
    state = FilterState(StateLayout("biases"))
    state.cov = np.diag(np.linspace(1e-6, 1.0, state.dim))
    return state


def test_state_problem_finds_what_makes_a_state_untrustworthy():
    assert state_problem(sound_state()) is None
    state = sound_state()
    state.p[1] = np.nan
    assert state_problem(state) == "nominal p not finite"
    state = sound_state()
    state.cov[4, 4] = -1e-3
    assert "non-positive variance (index 4)" in state_problem(state)
    state = sound_state()
    state.cov[0, 1] = state.cov[1, 0] = 2.0 * np.sqrt(state.cov[0, 0] * state.cov[1, 1])  # correlation 2
    assert state_problem(state) == "covariance not positive definite"
    state = sound_state()
    state.cov[2, 3] = np.inf
    assert state_problem(state) == "covariance not finite"


def test_gap_variance_grows_with_the_gap_and_more_when_the_state_is_held():
    opts = HealthOptions()
    short, longer = (gap_variances(dt, 8.0, 0.1, opts, extrapolated=True) for dt in (0.5, 1.0))
    assert np.all(longer > short) and longer[0] == pytest.approx((0.5 * 2.0 * 1.0) ** 2)
    held = gap_variances(1.0, 8.0, 0.1, opts, extrapolated=False)
    assert held[0] == pytest.approx(longer[0] + 8.0**2) and held[1] == longer[1] and held[2] > longer[2]


def test_gap_widener_adds_each_part_of_a_gap_once_and_says_when_to_reset():
    opts = HealthOptions(imu_gap_reset_s=1.0)
    state = sound_state()
    before = state.cov.diagonal().copy()
    widener = GapWidener(opts, bridge_s=0.05)
    assert not widener.widen(state, 0.04, np.zeros(3))  # within the bridge: nothing
    assert not widener.widen(state, 0.6, np.zeros(3))
    once = state.cov.diagonal().copy()
    assert not widener.widen(state, 0.6, np.zeros(3))  # the same instant again: nothing more
    assert np.array_equal(state.cov.diagonal(), once)
    assert widener.widen(state, 1.5, np.zeros(3)) and widener.holding  # past the limit: reset, hold
    assert not widener.widen(state, 2.0, np.zeros(3))  # reported once per gap
    grown = state.cov.diagonal() - before
    assert grown[0] == pytest.approx((0.5 * 2.0 * 1.5**2) ** 2 + (0.5 * 2.0 * 2.0**2) ** 2 - (0.5 * 2.0 * 1.5**2) ** 2)
    assert np.all(grown[9:] == 0.0)  # biases are not touched by a gap
    widener.end()
    assert not widener.holding and widener.covered_s == 0.0


def test_monitor_stale_sensors_and_resets_cap_the_quality():
    opts = HealthOptions(gps_stale_s=1.0, stale_quality_cap=50, reset_quality_cap=20, reset_hold_s=5.0)
    mon = HealthMonitor(opts, gps_reset_after_s=5.0)
    assert mon.quality_cap(0) == 100  # nothing seen, nothing stale
    assert not mon.measured("gps", 1 * S, used=True)
    assert mon.quality_cap(int(1.9 * S)) == 100 and mon.fresh("gps", int(1.9 * S))
    assert mon.quality_cap(int(2.1 * S)) == 50 and mon.stale(int(2.1 * S)) == ["gps"]
    for k in range(2, 8):  # gate rejections for 5 s: the estimate is wrong, reset
        reset = mon.measured("gps", k * S, used=False, gated=True)
        assert reset == (k == 7)
    mon.record_reset(7 * S, "gps_rejected", "test")
    assert mon.quality_cap(8 * S) == 20 and mon.quality_cap(13 * S) == 50
    report = mon.report(8 * S)
    assert report["resets"] == {"gps_rejected": 1} and report["degraded"] == ["gps_stale", "recent_reset_gps_rejected"]
    assert report["sensors"]["gps"]["stale"] and report["sensors"]["gps"]["age_s"] == 1.0
    assert not mon.measured("gps", 8 * S, used=False, gated=False)  # non-finite fixes never reset


def test_quality_caps_over_a_run_of_times_are_the_cap_at_each():
    """The caps of a run's steps, worked out once where no limit falls among their times, are the cap at each
    time, also across every edge (a sensor going stale, an innovation run capped, a reset's hold ending, the
    IMU missing), with an edge at, or a nanosecond beside, the first, second or last time."""
    opts = HealthOptions(gps_stale_s=1.0, stale_quality_cap=50, reset_quality_cap=20, reset_hold_s=2.0,
                         innovation_cap_s=1.0, innovation_quality_cap=40)
    mon = HealthMonitor(opts, gps_reset_after_s=5.0)
    edges = [S + 1, 4 * S, 8 * S]  # stale from 1 s + 1 ns on; capped from 4 s on; the reset's hold ends at 8 s

    def check() -> set[int]:
        seen = set()
        for step in (1, S // 100, S // 3):
            for t0 in [0, *[e + d - k * step for e in edges for d in (-1, 0, 1) for k in (0, 1, 11)]]:
                times = list(range(t0, t0 + 12 * step, step))
                caps = [mon.quality_cap(t) for t in times]
                assert mon.quality_caps(times) == caps, (t0, step)
                seen.update(caps)
        return seen
    assert check() == {100}
    mon.measured("gps", 0, used=True)
    assert check() == {100, 50}
    mon.innovations("camera", 3 * S, False, "test")
    assert check() == {100, 50, 40}
    mon.record_reset(6 * S, "test", "test")
    assert check() == {20, 50}  # a reset ends the innovation run
    mon.imu_missing(8 * S)
    assert check() == {0}


def test_camera_frames_are_judged_by_reobservation_nis_and_churn():
    opts = HealthOptions()
    frame = FrameInnovations(0, in_view=20, matched=12, initialised=3, nis=20.0, dof=24)
    assert camera_verdict(frame, [frame], opts) == (True, "")
    few = FrameInnovations(0, in_view=5, matched=0, initialised=0, nis=float("nan"), dof=0)
    assert camera_verdict(few, [few], opts)[0] is None  # too little in view to say anything
    lost = FrameInnovations(0, in_view=20, matched=2, initialised=3, nis=1.0, dof=4)
    verdict, why = camera_verdict(lost, [lost], opts)
    assert verdict is False and "2 of 20 landmarks in view re-observed" in why
    wild = FrameInnovations(0, in_view=20, matched=12, initialised=0, nis=80.0, dof=24)  # χ²(24) 99.9 %: 51.2
    assert camera_verdict(wild, [wild], opts)[0] is False and "NIS" in camera_verdict(wild, [wild], opts)[1]
    churning = [FrameInnovations(k, in_view=3, matched=1, initialised=8, nis=float("nan"), dof=2) for k in range(4)]
    verdict, why = camera_verdict(churning[-1], churning, opts)
    assert verdict is False and "32 landmarks initialised in the last second for 4 matches" in why


def test_innovations_out_of_band_cap_the_quality_after_a_second_and_reset_after_three():
    mon = HealthMonitor(HealthOptions(innovation_cap_s=1.0, innovation_quality_cap=50, innovation_reset_s=3.0), 3.0)
    good = FrameInnovations(0, 20, 15, 2, 10.0, 30)
    assert mon.camera_frame(good) == (False, "")
    t = 0
    lost = False
    while not lost:
        t += S // 8
        lost, why = mon.camera_frame(FrameInnovations(t, 20, 1, 2, 1.0, 2))
        assert mon.quality_cap(t) == (50 if t - S // 8 >= S else 100)
        assert t <= 4 * S
    assert t == S // 8 + 3 * S and "re-observed" in why
    report = mon.report(t)
    assert "camera_innovations" in report["degraded"] and report["innovations_out_of_band"]["camera"]["out_of_band_s"] == 3.0
    mon.record_reset(t, "camera_lost", why)
    assert mon.out_of_band(t) == [] and mon.runs["camera"].capped == 1
    # In band again ends a run; no verdict (little in view) neither starts nor ends one.
    assert not mon.innovations("gps", 10 * S, False, "refused") and mon.out_of_band(10 * S)[0][0] == "gps"
    assert not mon.innovations("gps", 11 * S, None)
    assert mon.quality_cap(int(11.5 * S)) == 50
    assert not mon.innovations("gps", 12 * S, True) and mon.out_of_band(12 * S) == []


def test_health_options_are_checked():
    with pytest.raises(ValueError, match="imu_gap_reset_s"):
        HealthOptions(imu_gap_reset_s=0.0)
    with pytest.raises(ValueError, match="quality caps"):
        HealthOptions(stale_quality_cap=101)
    with pytest.raises(ValueError, match="innovation_cap_s"):
        HealthOptions(innovation_cap_s=4.0, innovation_reset_s=3.0)


# ------------------------------------------------------------------------ the filter


@pytest.fixture(scope="module")
def flight():
    return simulate_flight("landfill", 40.0, 5)


def feed(est: Estimator, flight, t_from_s: float, t_to_s: float) -> None:
    for sample in flight_samples(flight, t_from_s, t_to_s):
        if isinstance(sample, ImuSample):
            est.process_imu(sample.t_ns, sample.gyro, sample.accel)
        else:
            est.process_gps(sample)


def estimator(flight) -> Estimator:
    return Estimator(flight.calibration, filter_options(load_config(), flight.calibration.imu.noise))


@pytest.mark.parametrize("breakage", ["covariance", "nominal"])
def test_a_broken_filter_state_is_rebuilt_and_counted(flight, breakage):
    est = estimator(flight)
    feed(est, flight, 0.0, 30.0)
    assert est.reset_counter == 0 and est.health.snapshot is not None
    good_p = est.health.snapshot.p.copy()
    if breakage == "covariance":
        est.state.cov[0, 0] = -1.0
    else:
        est.state.p[:] = np.nan
        est.state.cov[:] = np.nan
    feed(est, flight, 30.0, 40.0)
    assert est.reset_counter == 1 and est.health.reset_counts == {"state_invalid": 1}
    assert state_problem(est.state) is None and est.state.is_finite()
    assert "reset #1" in est.events[-1].message or any("reset #1" in e.message for e in est.events)
    truth_p = flight.truth.p[-1]
    assert np.linalg.norm(est.state.p - truth_p) < 5.0  # back on the GPS
    if breakage == "nominal":
        assert np.linalg.norm(good_p - truth_p) > 1.0  # (it started from the snapshot, then GPS pulled it)


# ------------------------------------------------------------------------ isolation


class Broken(PoseList):
    """An output whose link has died: every publish raises."""

    name = "broken"

    def publish(self, pose) -> None:
        raise ConnectionResetError("link down")


def samples(flight, t_to_s: float):
    return flight_samples(flight, 0.0, t_to_s)


async def from_list(items, fail_after: int | None = None):
    for k, item in enumerate(items):
        if fail_after is not None and k == fail_after:
            raise OSError("device unplugged")
        yield item
        await asyncio.sleep(0)


def test_a_failing_output_is_isolated_counted_and_logged_once(flight, caplog):
    good, broken = PoseList(), Broken()
    runtime = Runtime(estimator(flight), RuntimeOptions(fusion=FusionOptions(delay_s=0.1)), outputs=[broken, good])
    with caplog.at_level(logging.ERROR):
        summary = asyncio.run(runtime.run([from_list(samples(flight, 12.0))]))
    assert summary.poses_published > 1000 and len(good.poses) == summary.poses_published
    report = summary.status["failures"]
    assert report["output broken"]["failures"] == summary.poses_published
    assert report["output broken"]["last"] == "ConnectionResetError: link down"
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and errors[0].exc_info is not None  # the first with its traceback, no flood


def test_a_failing_source_ends_alone_and_the_others_go_on(flight):
    items = samples(flight, 12.0)
    imu = [s for s in items if isinstance(s, ImuSample)]
    gps = [s for s in items if isinstance(s, GpsFix)]
    out = PoseList()
    runtime = Runtime(estimator(flight), RuntimeOptions(fusion=FusionOptions(delay_s=0.1), lockstep=True), outputs=[out])
    summary = asyncio.run(runtime.run([from_list(imu), from_list(gps, fail_after=20)]))
    assert summary.imu_samples == len(imu)
    assert summary.status["failures"]["source 1"]["last"] == "OSError: device unplugged"
    assert runtime.est.counts["gps"].received == 20


def test_a_sample_whose_handling_raises_is_skipped(flight):
    items = samples(flight, 6.0)
    mid = len(items) // 2
    items.insert(mid, ImuSample(items[mid - 1].t_ns + 1, None, None))  # a driver bug: no arrays at all
    out = PoseList()
    runtime = Runtime(estimator(flight), RuntimeOptions(fusion=FusionOptions(delay_s=0.1)), outputs=[out])
    summary = asyncio.run(runtime.run([from_list(items)]))
    assert summary.status["failures"]["handling ImuSample"]["failures"] == 1
    assert out.poses[-1].t_ns == max(s.t_ns for s in items if isinstance(s, ImuSample) and s.gyro is not None)


def test_failure_book_summarises_a_flood_once_per_period(caplog):
    now = [0.0]
    book = FailureBook(period_s=10.0, clock=lambda: now[0])
    with caplog.at_level(logging.ERROR):
        for k in range(2000):  # 200 failures a second for 10 s
            now[0] = k * 0.005
            book.record("output zenoh", RuntimeError(f"#{k}"))
        now[0] = 10.0
        book.record("output zenoh", RuntimeError("late"))
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and "2000 more failure(s)" in lines[1] and "late" in lines[1]
    assert book.report() == {"output zenoh": {"failures": 2001, "last": "RuntimeError: late"}}
    assert str(book.first("output")) == "#0"


def test_published_quality_never_exceeds_the_health_cap(flight):
    out = PoseList()
    runtime = Runtime(estimator(flight), RuntimeOptions(fusion=FusionOptions(delay_s=0.1)), outputs=[out])
    summary = asyncio.run(runtime.run([from_list(samples(flight, 12.0))]))
    sharp = dataclasses.replace(out.poses[-1], cov9=np.eye(9) * 1e-6)
    assert pose_quality(sharp) == 100
    assert pose_quality(dataclasses.replace(sharp, quality_cap=20)) == 20
    assert summary.status["quality"] == pose_quality(out.poses[-1])
    assert summary.status["health"]["sensors"]["gps"]["used"] > 0
