"""One simulated flight: truth, IMU and GPS arrays plus the calibration that describes them.

``simulate_flight`` is what ``vtolpose simulate`` calls; writing the dataset is
``vtolpose.drivers.files.dataset``'s job. Determinism: each sensor draws from its own PCG64 stream, seeded by
``SeedSequence(seed, spawn_key=(stream,))`` with a fixed stream number per sensor, so the same
seed gives identical arrays and a sensor added later (camera: stream 2, LIDAR: 4) changes nothing else.
"""

from __future__ import annotations


from dataclasses import dataclass, field, replace

import numpy as np

from vtolpose.drivers.simulator.gps_model import GpsErrorModel, antenna_positions, gps_errors
from vtolpose.drivers.simulator.imu_model import ImuErrorModel, bias_at, corrupt_imu
from vtolpose.drivers.simulator.scenarios import Scenario, make_scenario
from vtolpose.drivers.files.series import GpsSeries, ImuSeries, TruthSeries
from vtolpose.drivers.simulator.trajectory import Kinematics, Trajectory
from vtolpose.estimator.core.calibration import STANDARD_GRAVITY, Calibration, GpsCalibration, ImuCalibration

STREAM_IMU = 0
STREAM_GPS = 1
STREAM_CAMERA = 2  # reserved for the renderer
STREAM_HEADING = 3
STREAM_LIDAR = 4  # the LIDAR's range noise (drivers.simulator.lidar)


@dataclass(frozen=True, slots=True)
class SimulationOptions:
    """Everything about a simulation that is not the scenario, duration or seed.

    ``gps=None`` takes the scenario's receiver (book: σ_h 2 cm, no lever arm; landfill: σ_h
    1 m, antenna 0.3 m above the IMU). ``start_s`` > 0 begins the recording that far into the
    scenario's trajectory, in flight (a service restarted in the air): no rest at the start,
    and no stated heading, since no crew enters one mid-flight.
    """

    imu: ImuErrorModel = field(default_factory=ImuErrorModel)
    gps: GpsErrorModel | None = None
    truth_rate_hz: float = 100.0
    epoch_ns: int = 1_000_000_000
    gravity: float = STANDARD_GRAVITY
    start_s: float = 0.0  # join the scenario's trajectory this far in (a flight that starts in the air)
    rest_s: float | None = None  # time at rest before the motion; None: the scenario's own

    def __post_init__(self) -> None:
        if not (np.isfinite(self.start_s) and self.start_s >= 0.0):
            raise ValueError(f"start_s must be finite and >= 0, got {self.start_s}")
        if self.rest_s is not None and not (np.isfinite(self.rest_s) and self.rest_s >= 0.0):
            raise ValueError(f"rest_s must be zero or positive, got {self.rest_s}")
        if not (np.isfinite(self.truth_rate_hz) and self.truth_rate_hz > 0.0):
            raise ValueError(f"truth_rate_hz must be positive, got {self.truth_rate_hz}")
        if self.epoch_ns <= 0:
            raise ValueError(f"epoch_ns must be positive so that every t_ns > 0, got {self.epoch_ns}")
        if not (np.isfinite(self.gravity) and self.gravity > 0.0):
            raise ValueError(f"gravity must be positive, got {self.gravity}")


@dataclass(frozen=True, slots=True)
class SimulatedFlight:
    """Arrays of one simulated flight, the calibration a dataset needs, and the world behind it.

    ``calibration.gps.origin_lla`` set means the GPS belongs on disk as WGS84 around that
    origin; None means local NED. ``trajectory`` gives exact poses at any time (camera frames).
    """

    scenario_name: str
    description: str
    scenario: Scenario
    trajectory: Trajectory
    imu: ImuSeries
    gps: GpsSeries
    truth: TruthSeries
    calibration: Calibration
    seed: int
    duration_s: float


def sample_times_ns(rate_hz: float, duration_s: float, epoch_ns: int) -> np.ndarray:
    """``epoch + round(k·1e9/rate)`` for every k with k/rate < duration (no drift from rounding)."""
    count = int(np.floor(duration_s * rate_hz + 1e-9))
    return epoch_ns + np.round(np.arange(count) * (1e9 / rate_hz)).astype(np.int64)


def _rng(seed: int, stream: int) -> np.random.Generator:
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=(stream,))))


@dataclass(frozen=True, slots=True)
class TimeShifted:
    """``trajectory`` from ``offset_s`` on: time 0 here is ``offset_s`` there (a flight joined in the air)."""

    trajectory: Trajectory
    offset_s: float

    def kinematics(self, t: np.ndarray) -> Kinematics:
        t = np.asarray(t, dtype=float)
        k = self.trajectory.kinematics(t + self.offset_s)
        return Kinematics(t, k.p, k.v, k.a, k.euler, k.euler_rate)


def _stated_heading(world: Scenario, trajectory: Trajectory, seed: int) -> float:
    """What the crew would enter before take-off: the truth plus an error of the scenario's stated
    accuracy, so that a filter trusting it stays honest."""
    sigma = float(np.radians(world.heading_sigma_deg))
    true_heading = trajectory.kinematics(np.zeros(1)).euler[0, 2]
    return float(np.angle(np.exp(1j * (true_heading + sigma * _rng(seed, STREAM_HEADING).standard_normal()))))


def simulate_flight(
    scenario: str | Scenario, duration_s: float, seed: int, options: SimulationOptions | None = None
) -> SimulatedFlight:
    """Fly ``scenario`` (a name, or a scenario built with its own settings) for ``duration_s`` seconds;
    same arguments, identical arrays."""
    if not (np.isfinite(duration_s) and duration_s > 0.0):
        raise ValueError(f"duration_s must be positive, got {duration_s}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    options = options or SimulationOptions()
    world = make_scenario(scenario) if isinstance(scenario, str) else scenario
    if options.rest_s is not None:
        world = replace(world, static_s=options.rest_s)
    gps_model = options.gps or world.gps_model()
    trajectory = world.trajectory(options.start_s + duration_s, options.gravity)
    if options.start_s > 0.0:
        trajectory = TimeShifted(trajectory, options.start_s)
    epoch = options.epoch_ns

    def seconds(t_ns: np.ndarray) -> np.ndarray:
        return (t_ns - epoch) * 1e-9

    t_imu = sample_times_ns(options.imu.rate_hz, duration_s, epoch)
    at_imu = trajectory.kinematics(seconds(t_imu))
    readings = corrupt_imu(
        at_imu.omega_b(), at_imu.specific_force_b(options.gravity), options.imu, _rng(seed, STREAM_IMU)
    )

    t_truth = sample_times_ns(options.truth_rate_hz, duration_s, epoch)
    at_truth = trajectory.kinematics(seconds(t_truth))
    truth = TruthSeries(
        t_truth,
        at_truth.p,
        at_truth.q(),
        at_truth.v,
        bias_g=bias_at(t_imu, readings.bias_gyro, t_truth),
        bias_a=bias_at(t_imu, readings.bias_accel, t_truth),
    )

    t_gps = sample_times_ns(gps_model.rate_hz, duration_s, epoch)
    at_gps = trajectory.kinematics(seconds(t_gps))
    antenna = antenna_positions(at_gps.p, at_gps.rotation(), gps_model)
    errors = gps_errors(seconds(t_gps), gps_model, _rng(seed, STREAM_GPS))
    n_gps = len(t_gps)
    gps = GpsSeries(
        t_gps, antenna + errors, np.full(n_gps, gps_model.sigma_h), np.full(n_gps, gps_model.sigma_v)
    )

    in_flight = options.start_s > 0.0
    calibration = Calibration(
        imu=ImuCalibration(rate_hz=options.imu.rate_hz, noise=options.imu.noise(), gravity=options.gravity),
        gps=GpsCalibration(lever_arm_b=np.array(gps_model.lever_arm_b, dtype=float), origin_lla=world.origin_lla),
        initial_heading_rad=None if in_flight else _stated_heading(world, trajectory, seed),
        initial_heading_sigma_rad=None if in_flight else float(np.radians(world.heading_sigma_deg)),
        initial_gyro_bias_sigma=float(options.imu.gyro_turn_on_bias_std) or None,  # the simulated unit's datasheet
    )
    start = f", starting in flight {options.start_s:g} s into the scenario" if in_flight else ""
    description = f"{world.description}; simulated {duration_s:g} s with seed {seed}{start}"
    return SimulatedFlight(
        scenario_name=world.name,
        description=description,
        scenario=world,
        trajectory=trajectory,
        imu=ImuSeries(t_imu, readings.gyro, readings.accel),
        gps=gps,
        truth=truth,
        calibration=calibration,
        seed=int(seed),
        duration_s=float(duration_s),
    )
