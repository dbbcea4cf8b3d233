"""The estimator's status snapshot and typed events: what the service reads, frozen, and in step with the filter."""

from __future__ import annotations

import dataclasses

import pytest

from vtolpose.drivers.simulator import simulate_flight
from vtolpose.estimator.core.measurements import GpsFix
from vtolpose.estimator.filter import Estimator, FilterOptions
from vtolpose.estimator.modes import FilterMode, HeadingMode
from vtolpose.estimator.smoothing.recorder import StepRecorder
from vtolpose.estimator.status import EventKind
from vtolpose.service.runtime.loop import Runtime
from vtolpose.service.runtime.step_taps import SmoothingPlan, StepTaps


def _feed(est: Estimator, flight, until_s: float) -> None:
    fixes = [GpsFix(int(t), p, float(h), float(v))
             for t, p, h, v in zip(flight.gps.t_ns, flight.gps.p_ned, flight.gps.sigma_h, flight.gps.sigma_v)]
    t_end, j = int(flight.imu.t_ns[0] + until_s * 1e9), 0
    for t, g, a in zip(flight.imu.t_ns, flight.imu.gyro, flight.imu.accel):
        if t > t_end:
            break
        while j < len(fixes) and fixes[j].t_ns <= t:
            est.process_gps(fixes[j])
            j += 1
        est.process_imu(int(t), g, a)


@pytest.fixture(scope="module")
def flight():
    return simulate_flight("book", 30.0, 2)


def test_before_the_start_nothing_is_claimed(flight):
    status = Estimator(flight.calibration, FilterOptions(heading_source="gps")).status()
    assert status.mode is FilterMode.WAITING and status.initialising and not status.heading_aligned
    assert status.t_ns is None and status.heading_sigma_deg is None and status.events == ()


def test_status_follows_the_filter_through_start_position_and_heading(flight):
    est = Estimator(flight.calibration, FilterOptions(heading_source="gps"))
    _feed(est, flight, 30.0)
    status = est.status()
    assert status.mode is FilterMode.GPS and status.position_initialized and not status.initialising
    assert status.heading is HeadingMode.PLACED and status.heading_aligned and status.heading_source == "heading bank"
    kinds = [e.kind for e in status.events]
    assert kinds[0] is EventKind.STARTED and EventKind.POSITION_INITIALISED in kinds
    placed = status.first(EventKind.HEADING_PLACED)
    assert placed is not None and placed.t_ns == status.heading_placement.t_ns
    assert placed.figures["heading_deg"] == pytest.approx(status.heading_placement.heading_deg)
    assert status.heading_sigma_deg == pytest.approx(status.heading_placement.sigma_deg, rel=2.0)
    assert status.reset_counter == est.reset_counter == 0
    assert status.counts["gps"]["used"] > 100 and status.gyro_bias is not None


def test_the_snapshot_is_frozen_and_does_not_follow_the_filter(flight):
    est = Estimator(flight.calibration, FilterOptions(heading_source="gps"))
    _feed(est, flight, 8.0)
    before = est.status()
    with pytest.raises(dataclasses.FrozenInstanceError):
        before.reset_counter = 3
    with pytest.raises(TypeError):
        before.counts["gps"] = {}
    _feed(est, flight, 30.0)
    assert len(est.status().events) > len(before.events)


def test_the_recorder_is_given_at_construction_and_sees_the_start(flight):
    steps = []
    est = Estimator(flight.calibration, recorder=StepRecorder(steps.append))
    _feed(est, flight, 6.0)
    est.finish_recording()
    assert steps and steps[0].segment == 0 and steps[-1].ends_segment
    assert steps[0].t_ns <= est.events[0].t_ns + 10_000_000  # from the filter's first step on
    assert not hasattr(est, "record_with")  # no way to hand one over later


def test_the_runtime_refuses_an_estimator_built_without_its_taps_recorder(flight):
    taps = StepTaps(SmoothingPlan(lag_s=1.0))
    with pytest.raises(ValueError, match="built with the step taps' recorder"):
        Runtime(Estimator(flight.calibration), taps=taps)
    runtime = Runtime(Estimator(flight.calibration, recorder=taps.recorder), taps=taps)
    assert runtime.smoother is taps.smoother and runtime.smoother is not None
