"""Flight simulator: exact truth, IMU and GPS for the ``book`` and ``landfill`` scenarios.

``simulate_flight(scenario, duration_s, seed, options)`` returns arrays and a calibration; the
dataset writer (``vtolpose.drivers.files.dataset``) puts them on disk and a renderer can later draw camera
frames from ``flight.trajectory`` over ``flight.scenario.ground_height``; ``lidar.simulate_lidar``
casts a line scanner's beams against the same ground.
"""

from vtolpose.drivers.simulator.flight import (
    GpsSeries,
    ImuSeries,
    SimulatedFlight,
    SimulationOptions,
    TruthSeries,
    simulate_flight,
)
from vtolpose.drivers.simulator.gps_model import GpsErrorModel
from vtolpose.drivers.simulator.imu_model import ImuErrorModel
from vtolpose.drivers.simulator.scenarios import SCENARIOS, BookScenario, LandfillScenario, make_scenario

__all__ = [
    "SCENARIOS",
    "BookScenario",
    "GpsErrorModel",
    "GpsSeries",
    "ImuErrorModel",
    "ImuSeries",
    "LandfillScenario",
    "SimulatedFlight",
    "SimulationOptions",
    "TruthSeries",
    "make_scenario",
    "simulate_flight",
]
