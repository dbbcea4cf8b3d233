"""Write a simulated flight as a dataset folder, the same layout a real recording has."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from vtolpose.drivers.files.dataset import DatasetWriter, refuse_existing_dataset
from vtolpose.drivers.files.lidar import LidarReturns
from vtolpose.drivers.simulator.flight import SimulatedFlight
from vtolpose.drivers.simulator.render import RenderOptions, render_frames
from vtolpose.estimator.core.calibration import CameraCalibration


def write_flight(
    flight: SimulatedFlight,
    out: str | Path,
    overwrite: bool = False,
    camera: CameraCalibration | None = None,
    render_options: RenderOptions | None = None,
    lidar: LidarReturns | None = None,
) -> Path:
    """Dataset with IMU, GPS (WGS84 when the scenario has a geodetic origin) and full truth.

    With ``camera`` the frames are rendered (``vtolpose.drivers.simulator.render``, needs scikit-image)
    into ``mav0/cam0`` and the camera's calibration goes into ``dataset.yaml``; IMU, GPS and
    truth are byte for byte the same either way. With ``lidar`` (``drivers.simulator.lidar.simulate_lidar``)
    its returns go into ``mav0/lidar0``.
    """
    out = Path(out)
    refuse_existing_dataset(out, overwrite)
    writer = DatasetWriter(out)
    name = f"{flight.scenario_name}-seed{flight.seed}"
    calibration = flight.calibration if camera is None else dataclasses.replace(flight.calibration, camera=camera)
    writer.write_calibration(calibration, name, flight.description)
    writer.write_imu(flight.imu)
    writer.write_gps(flight.gps, geodetic_origin=flight.calibration.gps.origin_lla)
    writer.write_truth(flight.truth)
    if camera is not None:
        writer.write_camera_frames(render_frames(flight, camera, render_options))
    if lidar is not None:
        writer.write_lidar(lidar)
    return out
