"""On the pad, the camera's matches without parallax are a zero-velocity update: they must leave the accelerometer
bias as well known as the rest alone does, or the climb that follows reads the bias's error as a climb rate."""

from __future__ import annotations

import math

import pytest

pytest.importorskip("cv2", reason="the camera pipeline needs OpenCV")

from vtolpose.config import load_config  # noqa: E402
from vtolpose.drivers.files.dataset import Dataset  # noqa: E402
from vtolpose.service.replay.session import replay  # noqa: E402

BA_DOWN = 14  # the accelerometer bias's down component in the biases model's error state


def test_the_camera_on_the_pad_leaves_the_accelerometer_bias_as_known_as_the_rest_does(flight_folder) -> None:
    # The landfill's first 10 s on the pad (seed 3, the flight whose climb ran 0.49 m high with the camera: the
    # camera's matches held the bias while they pinned the velocity, so the rest's zero-velocity updates found
    # nothing left to tell it: 0.027 m/s^2 of vertical sigma against 0.002 without the camera).
    dataset = Dataset.open(flight_folder("landfill", 10.0, 3, camera=True))
    cfg = load_config(None, None)
    sigma = {}
    for name, sensors in (("imu+gps", ["imu", "gps"]), ("imu+camera+gps", ["imu", "camera", "gps"])):
        result = replay(dataset, cfg, sensors)
        state = result.estimator.state
        assert state.layout.estimates_biases and result.estimator.reset_counter == 0
        sigma[name] = math.sqrt(state.cov[BA_DOWN, BA_DOWN])
    assert sum(f.accepted for f in result.frames) > 20  # the camera was in use on the pad
    assert sigma["imu+camera+gps"] <= 1.2 * sigma["imu+gps"], sigma
