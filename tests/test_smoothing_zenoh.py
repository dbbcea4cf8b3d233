"""Fixed-lag smoothing through the daemon, over Zenoh on loopback: ``pose/at`` for one time answers
first with a prediction or the filtered pose, and with the smoothed pose once the lag has passed."""

import asyncio
import threading
import time

import numpy as np
import pytest

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.estimator.metrics import interpolate_poses
from vtolpose.service.outputs.pose_client import PoseUnavailable
from vtolpose.service.runtime.replay_feed import replay_async

from conftest import free_port, pose_client_when_listening

LAG_S = 1.0
STEPS_PER_SAMPLE = 4


@pytest.fixture(scope="module")
def flight_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("smooth") / "book"
    write_flight(simulate_flight("book", 9.0, 4), root)
    return root


@pytest.mark.slow
def test_pose_at_switches_from_filtered_to_smoothed_once_the_lag_has_passed(flight_dir):
    port = free_port()
    cfg = load_config(overrides={
        "outputs": {"zenoh": {"enabled": True, "listen": [f"tcp/127.0.0.1:{port}"], "multicast_scouting": False}},
        "smoothing": {"fixed_lag_s": LAG_S, "steps_per_sample": STEPS_PER_SAMPLE, "max_window_s": 5.0},
    })
    dataset = Dataset.open(flight_dir)
    t0 = int(dataset.imu_raw().t_ns[0])
    t_star = t0 + 5_000_000_000  # the filter starts after a 2 s still window; by 5 s it tracks GPS
    service = threading.Thread(target=lambda: asyncio.run(replay_async(
        dataset, cfg, sensors=["imu", "gps"], speed=1.0, handle_signals=False, hold=True, duration_s=11.0)), daemon=True)
    service.start()
    answers, newest = [], [0]
    deadline = time.monotonic() + 10.0
    client = pose_client_when_listening(port)
    with client:
        client.subscribe(lambda pose: newest.__setitem__(0, max(newest[0], pose.t_ns)))
        while time.monotonic() < deadline and not (answers and answers[-1][1].kind == "smoothed"):
            try:
                answers.append((newest[0], client.pose_at(t_star)))
            except (PoseUnavailable, TimeoutError):  # t_star not in the history yet, or the answer late: ask again
                pass
            time.sleep(0.02)
        window = client.trajectory(t_star - 100_000_000, t_star)
    service.join(15.0)
    kinds = [a.kind for _, a in answers]
    assert kinds and kinds[-1] == "smoothed", kinds
    order = ["predicted", "filtered", "smoothed"]
    assert [order.index(k) for k in kinds] == sorted(order.index(k) for k in kinds)  # never back to a worse kind
    assert "filtered" in kinds
    first_smoothed = kinds.index("smoothed")
    newest_then = answers[first_smoothed][0]
    s = STEPS_PER_SAMPLE * 2  # IMU at 125 Hz, filter steps at 62.5 Hz: two calls per step
    # The newest published pose runs fusion.delay_s (0.15 s) ahead of the filter the lag counts from, and may
    # reach this subscriber a little late on a busy machine (the lower bound allows for that).
    assert LAG_S - 0.25 <= (newest_then - t_star) * 1e-9 <= LAG_S * (s + 1) / (s - 1) + 0.15 + 0.3
    filtered = next(a for _, a in reversed(answers[:first_smoothed]) if a.kind == "filtered")
    smoothed = answers[-1][1]
    assert not np.allclose(filtered.p, smoothed.p)  # later data moved it
    assert np.trace(smoothed.cov[:3, :3]) < np.trace(filtered.cov[:3, :3])
    truth_p, _ = interpolate_poses(np.array([t_star]), dataset.truth().t_ns, dataset.truth().p)
    assert np.linalg.norm(smoothed.p - truth_p[0]) < 0.05
    up_to = window.t_ns <= t_star  # the entry after t_star that brackets it may still be filtered
    assert up_to.sum() > 3 and set(window.kind[up_to].tolist()) == {"smoothed"}
    assert window.cov.shape == (len(window), 6, 6)
