"""A camera frame's update on the fusion thread: the poses keep leaving meanwhile, from the detached prediction,
and the filter ends where the loop alone would have taken it."""

import asyncio
import threading

import numpy as np
import pytest

from vtolpose.config import load_config
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.estimator.core.measurements import CameraFrame, GpsFix, ImuSample
from vtolpose.estimator.filter import Estimator
from vtolpose.estimator.fusion import FusionCore, FusionOptions
from vtolpose.service.runtime.fusion_thread import MAX_HELD, FusionThread
from vtolpose.service.runtime.loop import Runtime, RuntimeOptions
from vtolpose.service.runtime.sources import ReplayClock
from vtolpose.service.runtime.wiring import filter_options

from runtime_helpers import PoseList, flight_samples


@pytest.fixture(scope="module")
def flight():
    return simulate_flight("landfill", 16.0, 11)


def started_estimator(flight) -> Estimator:
    return Estimator(flight.calibration, filter_options(load_config(), flight.calibration.imu.noise))


async def paced(items):
    clock = ReplayClock(1.0)
    for item in items:
        await clock.wait_until(item.t_ns)
        yield item


def run_with_a_slow_frame(flight, update_thread: bool) -> tuple[Runtime, list, dict]:
    """12 s to start, then 2 s in real time with 7.5-Hz frames whose first update takes 0.1 s (under a frame
    period and the fusion delay: on the loop too, no frame is lost), each a GPS fix of the flight fused as the
    frame's measurement, so that the update changes the filter."""
    warm = flight_samples(flight, 0.0, 12.0)
    live = flight_samples(flight, 12.0, 14.0, frames=True)
    fixes = [s for s in live if isinstance(s, GpsFix)]
    seen: dict = {"threads": set(), "poses_during": [], "where": [], "end": live[-1].t_ns, "on_frame": []}
    fused: list = []

    class Extract:
        """The camera work: its update calls the processor's ``on_frame`` (viewers, an MCAP file), as the service's does."""

        def on_frame(self, t_ns: int) -> None:
            seen["on_frame"].append(threading.current_thread().name)

        def __call__(self, frame: CameraFrame):
            return apply_for(frame)

    extract = Extract()

    def apply_for(frame: CameraFrame):
        def apply(est: Estimator) -> None:
            extract.on_frame(frame.t_ns)
            seen["threads"].add(threading.current_thread().name)
            seen["where"].append((frame.t_ns, threading.current_thread().name))
            if frame.seq == 0:  # the slow one: the loop must not wait for it
                before = runtime.poses_published
                threading.Event().wait(0.1)
                seen["poses_during"].append(runtime.poses_published - before)
            fix = min(fixes, key=lambda f: abs(f.t_ns - frame.t_ns))
            est.process_gps(GpsFix(frame.t_ns, fix.p_ned + 0.01, fix.sigma_h, fix.sigma_v))
        return apply

    options = RuntimeOptions(fusion=FusionOptions(delay_s=0.15), update_thread=update_thread)
    runtime = Runtime(started_estimator(flight), options, outputs=[PoseList()], camera_processor=extract,
                      on_fused=fused.append)
    for s in warm:
        runtime.handle(s)
    asyncio.run(runtime.run([paced(live)]))
    return runtime, fused, seen


def test_a_slow_frame_update_on_the_fusion_thread_leaves_every_pose_going_and_fuses_as_the_loop_alone(flight):
    threaded, fused_threaded, seen = run_with_a_slow_frame(flight, update_thread=True)
    alone, fused_alone, seen_alone = run_with_a_slow_frame(flight, update_thread=False)
    # On the thread while the run goes on; the flush at the end (no pose leaves any more) fuses the frames the
    # horizon had not reached yet on the loop.
    horizon = seen["end"] - threaded.fusion.delay_ns
    assert {name for t, name in seen["where"] if t <= horizon} == {"fusion_0"}
    assert {name for t, name in seen["where"] if t > horizon} == {threading.main_thread().name}
    assert seen_alone["threads"] == {threading.main_thread().name}
    # What the update hands to viewers and recorders reaches them on the loop, one writer for each.
    assert set(seen["on_frame"]) == {threading.main_thread().name} and len(seen["on_frame"]) == 15
    # 0.1 s at 125 Hz: poses left all along on the thread's watch, none while the loop did the update itself.
    assert seen["poses_during"][0] >= 8 and seen_alone["poses_during"] == [0]
    assert threaded.poses_published == alone.poses_published  # a pose for every sample either way
    published = [pose.t_ns for pose in threaded.outputs[0].poses]
    assert published == sorted(set(published))
    on_thread = sum(name == "fusion_0" for _, name in seen["where"])
    assert 10 <= threaded.status_document()["fusion_thread"]["advances"] <= on_thread  # one may fuse two frames
    # The filter took the same inputs in the same order: the same fused poses, to the bit.
    assert len(fused_threaded) == len(fused_alone) > 800
    for a, b in zip(fused_threaded, fused_alone):
        assert a.t_ns == b.t_ns
        np.testing.assert_array_equal(np.concatenate([a.p, a.v, a.q]), np.concatenate([b.p, b.v, b.q]))
    assert threaded.fusion.counts["camera"].used == alone.fusion.counts["camera"].used == 15


def test_the_detached_prediction_steps_as_the_fusion_core_predicts(flight):
    """Cut loose, the prediction takes each sample as the fusion core's own predictor does: the same pose."""
    core = FusionCore(started_estimator(flight), FusionOptions(delay_s=0.15))
    samples = [s for s in flight_samples(flight, 0.0, 12.0) if isinstance(s, ImuSample)]
    for s in samples[:-50]:
        core.add_imu(s) if isinstance(s, ImuSample) else None
    core.output()
    detached = core.detached()
    for s in samples[-50:]:
        core.add_imu(s, fuse=False)  # the horizon stays: no measurement, the core's prediction just steps
        detached.step(s.t_ns, s.gyro, s.accel)
        mine, theirs = detached.output(), core.output()
        assert mine.t_ns == theirs.t_ns == s.t_ns
        np.testing.assert_array_equal(np.concatenate([mine.p, mine.v, mine.q, mine.omega_b]),
                                      np.concatenate([theirs.p, theirs.v, theirs.q, theirs.omega_b]))
        assert (mine.heading_aligned, mine.reset_counter) == (theirs.heading_aligned, theirs.reset_counter)


class _Core:
    """What the thread needs of a fusion core: its callbacks and an advance (here one that fails)."""

    def __init__(self) -> None:
        self.on_fused, self.on_fused_run = print, None

    def detached(self) -> None:
        return None

    def advance(self) -> None:
        self.on_fused("a pose")
        raise RuntimeError("the update failed")


def test_the_thread_hands_back_the_poses_and_the_failure_and_holds_a_bounded_number_of_inputs():
    core, results = _Core(), []
    thread = FusionThread()

    async def go() -> None:
        thread.hand_over(core, lambda fused, error: results.append((fused, error)))
        assert thread.busy
        assert all(thread.hold(lambda: None) for _ in range(MAX_HELD)) and not thread.hold(lambda: None)
        await thread.idle()

    asyncio.run(go())
    thread.close()
    (fused, error), = results
    assert fused == [(print, "a pose")] and isinstance(error, RuntimeError)
    assert core.on_fused is print and not thread.busy  # the core's own callbacks back
    assert len(thread.take_held()) == MAX_HELD and thread.report() == {"advances": 1, "held_dropped": 1}


def test_heavy_work_is_a_frame_behind_the_horizon_or_the_state_check_with_a_map(flight):
    """What goes to the thread: an advance that fuses a frame, or one in which the once-a-second state check
    factorises the covariance of a state with a map; an advance of IMU samples alone, or a check without a map,
    stays on the loop."""
    core = FusionCore(started_estimator(flight), FusionOptions(delay_s=0.15))
    imu = [s for s in flight_samples(flight, 0.0, 12.0) if isinstance(s, ImuSample)]
    for s in imu[:-250]:
        core.add_imu(s)
    est = core.est
    assert not est.state.n_landmarks and est.health.check_would_be_due(imu[-1].t_ns)
    est.state.landmarks = np.zeros((1, 6))  # a map (only its count is read here)
    verdicts = []
    for s in imu[-250:]:  # the horizon moves on, nothing is fused: the check falls due on the way
        core.add_imu(s, fuse=False)
        due = est.health.check_would_be_due(core.newest_imu_t_ns - core.delay_ns)
        verdicts.append((due, core.heavy_due()))
    assert {due for due, _ in verdicts} == {False, True} and all(due == heavy for due, heavy in verdicts)
    est.state.landmarks = np.zeros((0, 6))
    assert not core.heavy_due()  # no map: the check is microseconds
    horizon = core.newest_imu_t_ns - core.delay_ns
    core.add_measurement(horizon + 50_000_000, lambda e: None, "camera", fuse_now=False)
    assert not core.heavy_due()  # a frame the horizon has not reached
    core.add_measurement(horizon - 1_000_000, lambda e: None, "camera", fuse_now=False)
    assert core.heavy_due()
    core.advance()
    assert not core.heavy_due()
