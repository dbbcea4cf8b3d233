"""The camera joins a running filter only when the map it starts can be placed: after a start in motion (tilt
known to 5°) it waits for gravity to narrow the tilt, and the heading it then helps to find is as certain as
the filter says, not more.

A gentle hand-held path over a floor of photographs, started in motion with a stated heading 2° uncertain (and
4.5° wrong on this seed), GPS 2 cm at 10 Hz: the camera matrix's base cell, shortened. Its map started under
the 5° tilt made the camera's updates shrink the heading's sigma to 0.4° within a second while the heading
stayed 7° off (NEES 196 over the flight).
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("skimage", reason="rendering needs scikit-image (the 'sim' extra)")

from vtolpose.config import load_config  # noqa: E402
from vtolpose.drivers.files.dataset import Dataset  # noqa: E402
from vtolpose.drivers.simulator import SimulationOptions, simulate_flight  # noqa: E402
from vtolpose.drivers.simulator.cameras import matrix_camera  # noqa: E402
from vtolpose.drivers.simulator.export import write_flight  # noqa: E402
from vtolpose.drivers.simulator.floor import FloorScenario, start_options  # noqa: E402
from vtolpose.drivers.simulator.motion_profiles import PROFILES  # noqa: E402
from vtolpose.estimator.core.covariance import TH  # noqa: E402
from vtolpose.estimator.core.rotation import quat_to_rot  # noqa: E402
from vtolpose.estimator.filter import TILT_WEAK_SIGMA_RAD, Estimator  # noqa: E402
from vtolpose.service.replay.report import build_report  # noqa: E402
from vtolpose.service.replay.session import replay  # noqa: E402


@pytest.fixture(scope="module")
def floor(tmp_path_factory) -> Dataset:
    profile = PROFILES["gentle"]
    scenario = FloorScenario(profile=profile, photos=None)  # scikit-image's photographs: no ../shared needed
    options = SimulationOptions(imu=profile.imu_model(), **start_options("motion", scenario))
    flight = simulate_flight(scenario, 10.0, 1, options)
    root = tmp_path_factory.mktemp("floor") / "floor"
    return Dataset.open(write_flight(flight, root, camera=matrix_camera("radtan", 640, 360, 15.0)))


def _yaw(q: np.ndarray) -> float:
    R = quat_to_rot(q)
    return float(np.arctan2(R[1, 0], R[0, 0]))


def test_after_a_start_in_motion_the_camera_waits_for_the_tilt_and_the_heading_stays_honest(floor, monkeypatch):
    tilt_at_first_frame: list[float] = []
    process = Estimator.process_features

    def watched(est, features):
        report = process(est, features)
        if report.accepted and not tilt_at_first_frame:
            tilt_at_first_frame.append(float(np.sqrt(est.state.cov[TH.start, TH.start])))
        return report

    monkeypatch.setattr(Estimator, "process_features", watched)
    poses = []
    cfg = load_config(None, {})
    result = replay(floor, cfg, ["imu", "camera", "gps"], on_fused=poses.append)
    est = result.estimator
    assert est.counts["camera"].rejected.get("tilt_weak", 0) > 5  # it waited
    assert tilt_at_first_frame and tilt_at_first_frame[0] <= TILT_WEAK_SIGMA_RAD * 1.01
    truth = floor.truth()
    heading_nees = []
    for pose in poses[len(poses) // 2:]:  # the second half: the camera has been in for seconds
        k = np.searchsorted(truth.t_ns, pose.t_ns)
        error = (_yaw(pose.q) - _yaw(truth.q[min(k, len(truth.t_ns) - 1)]) + np.pi) % (2 * np.pi) - np.pi
        heading_nees.append(error**2 / pose.cov9[8, 8])
    assert np.mean(heading_nees) < 6.6  # χ²(1) at 99 %, on the mean: no heading claimed that the camera cannot see
    report = build_report(result, floor, cfg)
    assert report["reset_counter"] == 0 and report["nees"]["mean_in_band"]
