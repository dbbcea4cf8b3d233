"""The camera's time offset against the IMU clock, measured on a dataset's own frames and gyro.

``vtolpose calibrate timesync`` prints it; ``vtolpose import`` measures it when a recording comes
with a camera and states no offset (an ASL/EuRoC folder has no field for one), because a replay
with frames stamped tens of milliseconds late is not a little worse but lost: on the real
hand-held recording 52 ms uncorrected took a 3-m walk to 400 m.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.estimator import FrameRotations, TimeSyncOptions, TimeSyncResult

SIGNIFICANT_SIGMAS = 3.0  # a measured offset nearer zero than this many sigmas is noise: the stamps are kept


@dataclass(frozen=True, slots=True)
class Measured:
    """One measurement: the correlation's result and the frame rotations it was made from."""

    result: TimeSyncResult
    rotations: FrameRotations

    @property
    def significant(self) -> bool:
        return abs(self.result.offset_s) > SIGNIFICANT_SIGMAS * self.result.sigma_s


def measure(dataset: Dataset, options: TimeSyncOptions | None = None) -> Measured:
    """Correlate the camera's frame-to-frame rotation with the gyro's over the whole dataset.

    Raises ``ValueError`` without a camera, ``TimeSyncError`` (a ``ValueError``) when the record
    cannot show the offset sharply; its message says what to record instead.
    """
    from vtolpose.estimator import correlate, frame_rotations, TimeSyncOptions

    camera = dataset.calibration.camera
    if camera is None or not dataset.has_camera:
        raise ValueError(f"{dataset.root}: no camera (dataset.yaml camera: and mav0/cam0/data.csv are both needed)")
    imu = dataset.imu()
    frames = ((t, image) for t, path in dataset.camera_frames() if (image := dataset.load_frame(path)) is not None)
    rotations = frame_rotations(frames, camera)
    result = correlate(rotations, imu.t_ns, imu.gyro, camera.R_BC, options or TimeSyncOptions())
    return Measured(result, rotations)


def describe(m: Measured) -> str:
    r = m.result
    return (f"{r.offset_s * 1e3:+.2f} +- {r.sigma_s * 1e3:.2f} ms (correlation peak {r.peak:.3f} over {r.n_pairs} "
            f"frame pairs of gyro and camera rotation)")
