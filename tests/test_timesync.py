"""IMU–camera time offset by correlation, on rendered frames whose stamps are shifted by a known offset.

The flight is a timesync manoeuvre as the error message asks for: the camera, 0.75 m above the
book scene, swung about all axes (±11° roll and pitch, ±30° yaw, periods of 2.5-9 s). Frames are
drawn by the simulator's renderer at half the default resolution (faster; same optics scaled).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset, DatasetWriter
from vtolpose.drivers.files.series import ImuSeries
from vtolpose.drivers.simulator import ImuErrorModel, simulate_flight
from vtolpose.drivers.simulator.flight import sample_times_ns
from vtolpose.drivers.simulator.imu_model import corrupt_imu
from vtolpose.drivers.simulator.render import default_camera, render_frames
from vtolpose.drivers.simulator.trajectory import EulerTrajectory, SineMotion
from vtolpose.estimator.calibration.timesync import TimeSyncError, correlate, frame_rotations
from vtolpose.service.cli import main
from vtolpose.service.commands.importer import settle_camera_time_offset

G = 9.80665
SHIFT_NS = 37_000_000  # the camera stamps are this late: the offset to find is -37 ms
CAMERA = dataclasses.replace(default_camera(), width=328, height=247, fx=285.0, fy=285.0, cx=163.5, cy=123.0)


def swung_flight(duration_s: float, seed: int):
    """The book flight with its trajectory replaced by a camera swung about all axes."""
    base = simulate_flight("book", duration_s, seed)
    rng = np.random.default_rng(seed)
    freq = np.array([[1.1, 2.3], [1.3, 2.7], [0.7, 1.9]])
    position = SineMotion(np.array([0.0, 0.0, -0.75]), np.array([[0.05, 0.02], [0.05, 0.02], [0.03, 0.01]]),
                          0.9 * freq, rng.uniform(0, 6, (3, 2)), 2.0, 1.0)
    attitude = SineMotion(np.array([0.0, 0.0, 0.3]), np.array([[0.2, 0.06], [0.2, 0.06], [0.5, 0.1]]), freq,
                          rng.uniform(0, 6, (3, 2)), 2.0, 1.0)
    trajectory = EulerTrajectory(position, attitude)
    model = ImuErrorModel()
    t = sample_times_ns(model.rate_hz, duration_s, int(base.imu.t_ns[0]))
    k = trajectory.kinematics((t - t[0]) * 1e-9)
    errors = corrupt_imu(k.omega_b(), k.specific_force_b(G), model, rng)
    return dataclasses.replace(base, trajectory=trajectory, imu=ImuSeries(t, errors.gyro, errors.accel))


@pytest.fixture(scope="module")
def swung():
    flight = swung_flight(15.0, seed=1)
    frames = [(t + SHIFT_NS, image) for t, image in render_frames(flight, CAMERA)]
    return flight, frames


def test_offset_of_shifted_camera_stamps_is_found_within_2_ms(swung) -> None:
    flight, frames = swung
    rotations = frame_rotations(frames, CAMERA)
    assert rotations.pairs_skipped == 0
    result = correlate(rotations, flight.imu.t_ns, flight.imu.gyro, CAMERA.R_BC)
    # Measured: -36.8 ms ± 0.3 ms (seeds 1-5 over 20 s: -36.4 ... -37.0 ms).
    assert result.offset_s == pytest.approx(-SHIFT_NS * 1e-9, abs=0.002)
    assert 0.0 < result.sigma_s < 0.001
    assert result.peak > 0.99
    assert result.residual_rms < 1e-3  # rad per pair and axis: the frame rotations are right


def test_too_little_rotation_says_what_to_record() -> None:
    flight = simulate_flight("book", 6.0, seed=2)  # the book flight rests for its first 10 s
    rotations = frame_rotations(render_frames(flight, CAMERA), CAMERA)
    with pytest.raises(TimeSyncError, match=r"too little rotation to correlate.*record the camera .* turned about all"):
        correlate(rotations, flight.imu.t_ns, flight.imu.gyro, CAMERA.R_BC)


def test_frames_without_texture_are_counted_and_refused(swung) -> None:
    flight, _ = swung
    t = flight.imu.t_ns[0] + np.arange(40) * 133_333_333
    blank = [(int(ti), np.full((CAMERA.height, CAMERA.width), 120, np.uint8)) for ti in t]
    rotations = frame_rotations(blank, CAMERA)
    assert rotations.pairs_skipped == 39 and len(rotations.t0_ns) == 0
    with pytest.raises(TimeSyncError, match=r"only 0 frame pairs were tracked .*39 pairs without enough tracks"):
        correlate(rotations, flight.imu.t_ns, flight.imu.gyro, CAMERA.R_BC)


def test_cli_writes_the_offset_for_the_config(swung, tmp_path, capsys) -> None:
    flight, frames = swung
    writer = DatasetWriter(tmp_path / "swung")
    writer.write_calibration(dataclasses.replace(flight.calibration, camera=CAMERA), "swung", "timesync test")
    writer.write_imu(flight.imu)
    writer.write_camera_frames(frames)
    out = tmp_path / "sync.yaml"
    assert main(["calibrate", "timesync", str(tmp_path / "swung"), "--out", str(out)]) == 0
    assert out.with_suffix(".png").read_bytes().startswith(b"\x89PNG")  # the correlation figure
    assert load_config(out)["calibration.camera.time_offset_s"] == pytest.approx(-0.037, abs=0.002)
    assert "camera: time_offset_s: -0.03" in out.read_text()
    assert "correlation peak" in capsys.readouterr().out


def test_one_wrongly_decomposed_pair_does_not_make_a_swing(swung) -> None:
    flight, frames = swung
    rotations = frame_rotations(frames, CAMERA)
    clean = correlate(rotations, flight.imu.t_ns, flight.imu.gyro, CAMERA.R_BC)
    rotvec = rotations.rotvec.copy()
    rotvec[len(rotvec) // 2] = [3.0, 0.0, 0.0]  # a homography decomposed the wrong way: 3 rad in one pair
    broken = correlate(dataclasses.replace(rotations, rotvec=rotvec), flight.imu.t_ns, flight.imu.gyro, CAMERA.R_BC)
    assert broken.rate_rms == pytest.approx(clean.rate_rms, rel=0.05)  # 14x the swing's rate without the median gate
    assert broken.offset_s == pytest.approx(clean.offset_s, abs=0.001)


def _swung_dataset(root, flight, frames, offset_s: float = 0.0):
    writer = DatasetWriter(root)
    camera = dataclasses.replace(CAMERA, time_offset_s=offset_s)
    writer.write_calibration(dataclasses.replace(flight.calibration, camera=camera), "swung", "timesync test")
    writer.write_imu(flight.imu)
    writer.write_camera_frames(frames)
    return root


def test_import_measures_the_offset_and_writes_it(swung, tmp_path) -> None:
    flight, frames = swung
    root = _swung_dataset(tmp_path / "late", flight, frames)
    line = settle_camera_time_offset(root, None, keep_stamps=False)
    assert "measured and written to dataset.yaml" in line
    dataset = Dataset.open(root)
    assert dataset.calibration.camera.time_offset_s == pytest.approx(-SHIFT_NS * 1e-9, abs=0.002)
    assert "measured at import" in dataset.meta["description"]


def test_import_keeps_stamps_that_are_right_given_or_asked_for(swung, tmp_path) -> None:
    flight, frames = swung
    on_time = [(t - SHIFT_NS, image) for t, image in frames]
    root = _swung_dataset(tmp_path / "on_time", flight, on_time)
    line = settle_camera_time_offset(root, None, keep_stamps=False)
    assert "within 3 sigma of zero" in line and Dataset.open(root).calibration.camera.time_offset_s == 0.0
    late = _swung_dataset(tmp_path / "late", flight, frames)
    assert settle_camera_time_offset(late, None, keep_stamps=True).startswith("0 (--no-timesync")
    assert Dataset.open(late).calibration.camera.time_offset_s == 0.0
    assert settle_camera_time_offset(late, -0.04, keep_stamps=False) == "-40.00 ms, as given"
    assert Dataset.open(late).calibration.camera.time_offset_s == -0.04


def test_import_says_why_a_record_without_rotation_keeps_its_stamps(tmp_path) -> None:
    flight = simulate_flight("book", 6.0, seed=2)  # at rest
    root = _swung_dataset(tmp_path / "still", flight, list(render_frames(flight, CAMERA)))
    line = settle_camera_time_offset(root, None, keep_stamps=False)
    assert line.startswith("0, not measured: too little rotation to correlate") and "--camera-time-offset" in line
    assert Dataset.open(root).calibration.camera.time_offset_s == 0.0
