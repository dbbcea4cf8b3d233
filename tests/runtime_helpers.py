"""For runtime tests: a simulated flight as the time-ordered samples a runtime reads, and the
simplest real output (it keeps the poses it is given)."""

from __future__ import annotations

import numpy as np

from vtolpose.estimator.core.measurements import CameraFrame, GpsFix, ImuSample

FRAME_PERIOD_NS = int(1e9 / 7.5)


def flight_samples(flight, t_from_s: float, t_to_s: float, frames: bool = False) -> list:
    """IMU and GPS of ``flight`` in [t_from_s, t_to_s) from its first IMU sample, with blank 7.5 Hz frames
    if ``frames``; at equal times the IMU first, then GPS, then the camera (the replay's order)."""
    imu, gps = flight.imu, flight.gps
    t0 = int(imu.t_ns[0])
    lo, hi = t0 + int(t_from_s * 1e9), t0 + int(t_to_s * 1e9)
    out = [(int(t), 0, ImuSample(int(t), g, a)) for t, g, a in zip(imu.t_ns, imu.gyro, imu.accel) if lo <= t < hi]
    out += [(int(t), 1, GpsFix(int(t), p, float(h), float(v)))
            for t, p, h, v in zip(gps.t_ns, gps.p_ned, gps.sigma_h, gps.sigma_v) if lo <= t < hi]
    if frames:
        image = np.zeros((48, 64), np.uint8)
        out += [(t, 2, CameraFrame(t, image, k)) for k, t in enumerate(range(lo + 1_000_000, hi, FRAME_PERIOD_NS))]
    return [s for _, _, s in sorted(out, key=lambda e: (e[0], e[1]))]


class PoseList:
    name = "list"

    def __init__(self) -> None:
        self.poses = []

    def open(self) -> None:
        """A list has no link to open."""

    def publish(self, pose) -> None:
        self.poses.append(pose)

    def publish_status(self, status) -> None:
        """Only poses are under test."""

    async def serve(self, stop) -> None:
        await stop.wait()

    def close(self) -> None:
        """Nothing to release."""
