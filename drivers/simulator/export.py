"""Write a simulated flight as a dataset folder, the same layout a real recording has."""

from __future__ import annotations

from pathlib import Path

from drivers.dataset import DatasetWriter
from drivers.simulator.flight import SimulatedFlight


def write_flight(flight: SimulatedFlight, out: str | Path, overwrite: bool = False) -> Path:
    """Dataset with IMU, GPS (WGS84 when the scenario has a geodetic origin) and full truth."""
    out = Path(out)
    if (out / "dataset.yaml").exists() and not overwrite:
        raise FileExistsError(f"{out}: already holds a dataset (dataset.yaml); use --force to replace it")
    writer = DatasetWriter(out)
    name = f"{flight.scenario_name}-seed{flight.seed}"
    writer.write_calibration(flight.calibration, name, flight.description)
    writer.write_imu(flight.imu)
    writer.write_gps(flight.gps, geodetic_origin=flight.calibration.gps.origin_lla)
    writer.write_truth(flight.truth)
    return out
