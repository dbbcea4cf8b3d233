"""A line-scanning LIDAR on the simulated vehicle: every beam cast against the scenario's ground.

The scanner spins a mirror once per scan and fires a beam every angular step across its field
of view, so each return has its own time and is cast from the pose the vehicle has at that
instant (``flight.trajectory``, exact at any time). The beam is marched along the scenario's
height field ``ground_height(n, e)`` (:func:`cast_rays`) and the hit is refined by bisection to
well under a millimetre; then Gaussian range noise is added and the range rounded to the
scanner's resolution. Beams that hit nothing within the maximum range give no return.

Defaults per scenario (:data:`SCENARIO_LIDARS`):
- ``book``: the Hokuyo URG-04LX the thesis' platform carried (section 2.5). Its figures come
  from Hokuyo's URG-04LX specification sheet (240° scan, 0.36° steps, 100 ms per scan, 60–4095 mm,
  accuracy ±10 mm up to 1 m and ±1 % of the distance beyond) and the reply of its SCIP 2.0
  ``PP`` command (1024 steps per revolution, so the step is 360°/1024 = 0.3516°, and 600 rpm).
  Its sweep of 240° takes 66.7 ms of the 100 ms turn.
- ``landfill``: a survey-class line scanner under the helicopter, looking down across the track:
  90° field of view, 0.25° steps, 10 scans/s (a 25 ms sweep), range σ 2 cm, 1–150 m. At 45 m
  that is a 90 m wide swath (the lanes are 60 m apart) with returns 0.2–0.4 m apart across the
  track and 0.8 m along it.
Both scan in the body's y–z plane: the scanner's +x is body down, +y body right.

Determinism: the range noise comes from the simulator's LIDAR stream (``STREAM_LIDAR``), one draw
per beam in firing order whether or not it hits, so the same flight and seed give the same bytes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from vtolpose.drivers.files.lidar import LidarReturns, LidarSpec
from vtolpose.drivers.simulator.flight import STREAM_LIDAR, SimulatedFlight, _rng
from vtolpose.estimator.mapping.geometry import LidarMount, beam_vectors

# Scanner +x → body down, +y → body right, +z → body back: the scan plane is across the track.
R_BL_DOWN_ACROSS = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])

URG_04LX = LidarSpec(
    model="Hokuyo URG-04LX", fov_deg=240.0, step_deg=360.0 / 1024.0, scan_rate_hz=10.0,
    range_sigma_m=0.01, range_sigma_fraction=0.01, range_resolution_m=0.001, min_range_m=0.06, max_range_m=4.0,
    mount=LidarMount(R_BL_DOWN_ACROSS, np.array([-0.08, 0.0, 0.04])),
)
SURVEY_SCANNER = LidarSpec(
    model="survey line scanner", fov_deg=90.0, step_deg=0.25, scan_rate_hz=10.0,
    range_sigma_m=0.02, range_sigma_fraction=0.0, range_resolution_m=0.001, min_range_m=1.0, max_range_m=150.0,
    mount=LidarMount(R_BL_DOWN_ACROSS, np.array([0.25, 0.0, 0.35])),
)


@dataclass(frozen=True, slots=True)
class GroundMarch:
    """How to march a beam over a height field without stepping through it.

    A step along the beam is the clearance above the ground divided by how fast the gap can
    close: the beam's own descent plus ``max_slope`` (a bound on the ground's gradient) times
    its horizontal travel; never longer than ``max_step_m`` (so a step in the ground, which
    has no gradient bound, is not jumped over) nor shorter than ``min_step_m``.
    """

    max_slope: float
    max_step_m: float
    min_step_m: float
    bisections: int = 40

    def __post_init__(self) -> None:
        if not (self.max_slope > 0.0 and 0.0 < self.min_step_m <= self.max_step_m and self.bisections > 0):
            raise ValueError(f"ground march needs max_slope > 0 and 0 < min_step <= max_step, got {self}")


# Per scenario: the scanner it carries and how its ground is marched. The book's ground has
# steps (book 3.5 cm, table edge), so its beams advance at most 2 cm at a time; the landfill's
# ground is smooth with slopes below 0.3 (a test keeps that true).
SCENARIO_LIDARS: dict[str, tuple[LidarSpec, GroundMarch]] = {
    "book": (URG_04LX, GroundMarch(max_slope=1.0, max_step_m=0.02, min_step_m=0.001)),
    "landfill": (SURVEY_SCANNER, GroundMarch(max_slope=1.0, max_step_m=10.0, min_step_m=0.005)),
}


def default_lidar(scenario: str) -> LidarSpec:
    """The scanner the scenario's vehicle carries."""
    try:
        return SCENARIO_LIDARS[scenario][0]
    except KeyError:
        raise ValueError(f"no LIDAR for scenario {scenario!r}; known: {sorted(SCENARIO_LIDARS)}") from None


def lidar_with(spec: LidarSpec, **changes: float | None) -> LidarSpec:
    """``spec`` with the figures given (None leaves one as it is), e.g. from the command line."""
    return replace(spec, **{k: v for k, v in changes.items() if v is not None})


GroundFunction = Callable[[np.ndarray, np.ndarray], np.ndarray]


def cast_rays(origin: np.ndarray, direction: np.ndarray, ground: GroundFunction, max_range_m: float,
              march: GroundMarch) -> np.ndarray:
    """Distance along each unit ``direction`` from ``origin`` (N, 3, NED) to the ground; inf if beyond ``max_range_m``.

    A ray starting below the ground hits at 0.
    """
    origin = np.asarray(origin, dtype=float)
    direction = np.asarray(direction, dtype=float)
    n = len(origin)
    hit = np.full(n, np.inf)
    lo, hi = np.zeros(n), np.zeros(n)  # bracket: above the ground at lo, at or below it at hi
    closing = np.maximum(direction[:, 2], 0.0) + march.max_slope * np.hypot(direction[:, 0], direction[:, 1])
    t = np.zeros(n)
    active = np.arange(n)
    while active.size:
        o, d = origin[active], direction[active]
        ta = t[active]
        p = o + ta[:, None] * d
        clearance = np.asarray(ground(p[:, 0], p[:, 1]), dtype=float) - p[:, 2]
        below = clearance <= 0.0
        reached = active[below]
        hi[reached] = ta[below]
        beyond = ~below & (ta >= max_range_m)
        carry = ~below & ~beyond
        with np.errstate(divide="ignore"):
            step = np.where(closing[active] > 0.0, clearance / closing[active], march.max_step_m)
        step = np.clip(step, march.min_step_m, march.max_step_m)
        lo[active[carry]] = ta[carry]
        # The last step stops at max_range, which is checked once more; a ray checked there is done.
        t[active[carry]] = np.minimum(ta[carry] + step[carry], max_range_m)
        active = active[carry]
        if reached.size:
            at_start = hi[reached] == 0.0
            hit[reached[at_start]] = 0.0
            refine = reached[~at_start]
            a, b = lo[refine], hi[refine]
            o, d = origin[refine], direction[refine]
            for _ in range(march.bisections):
                m = 0.5 * (a + b)
                p = o + m[:, None] * d
                under = np.asarray(ground(p[:, 0], p[:, 1]), dtype=float) - p[:, 2] <= 0.0
                b = np.where(under, m, b)
                a = np.where(under, a, m)
            hit[refine] = 0.5 * (a + b)
    return np.where(hit <= max_range_m, hit, np.inf)


def scan_times_ns(spec: LidarSpec, duration_s: float, epoch_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Times (S, B) of every beam of every scan that starts within the flight, and the scan numbers (S,)."""
    scans = int(np.floor(duration_s * spec.scan_rate_hz + 1e-9))
    starts = epoch_ns + np.round(np.arange(scans) * (1e9 / spec.scan_rate_hz)).astype(np.int64)
    offsets = np.round(np.arange(spec.beams) * spec.beam_interval_s * 1e9).astype(np.int64)
    return starts[:, None] + offsets[None, :], np.arange(scans, dtype=np.int64)


def simulate_lidar(flight: SimulatedFlight, spec: LidarSpec | None = None, march: GroundMarch | None = None,
                   scans_per_chunk: int = 100) -> LidarReturns:
    """Every return of the flight's LIDAR (the scenario's default scanner unless ``spec`` is given)."""
    default_spec, default_march = SCENARIO_LIDARS.get(flight.scenario_name, (None, None))
    spec = spec or default_spec
    march = march or default_march
    if spec is None or march is None:
        raise ValueError(f"no LIDAR defaults for scenario {flight.scenario_name!r}: give the scanner and the march")
    epoch = int(flight.truth.t_ns[0])
    end = epoch + int(round(flight.duration_s * 1e9))
    times, scan_ids = scan_times_ns(spec, flight.duration_s, epoch)
    angles = spec.angles()
    beams_b = beam_vectors(angles) @ spec.mount.R_BL.T  # beam directions in the body
    rng = _rng(flight.seed, STREAM_LIDAR)
    parts: list[tuple[np.ndarray, ...]] = []
    for first in range(0, len(scan_ids), scans_per_chunk):
        t = times[first:first + scans_per_chunk]
        noise = rng.standard_normal(t.shape)  # one per beam fired, hit or not
        flat_t = t.reshape(-1)
        k = flight.trajectory.kinematics((flat_t - epoch) * 1e-9)
        R_WB = k.rotation()
        origin = k.p + R_WB @ spec.mount.t_BL
        beams = np.tile(beams_b, (len(t), 1))
        direction = np.einsum("nij,nj->ni", R_WB, beams)
        true_range = cast_rays(origin, direction, flight.scenario.ground_height, spec.max_range_m, march)
        measured = true_range + spec.range_sigma(np.where(np.isfinite(true_range), true_range, 0.0)) * noise.reshape(-1)
        if spec.range_resolution_m > 0.0:
            measured = np.round(measured / spec.range_resolution_m) * spec.range_resolution_m
        keep = (np.isfinite(true_range) & (measured >= spec.min_range_m) & (measured <= spec.max_range_m)
                & (flat_t < end))
        scan = np.repeat(scan_ids[first:first + scans_per_chunk], spec.beams)
        parts.append((flat_t[keep], scan[keep], np.tile(angles, len(t))[keep], measured[keep]))
    if not parts:
        return LidarReturns(spec, np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0),
                            flight.scenario_name)
    t_ns, scan, angle, rng_m = (np.concatenate(c) for c in zip(*parts))
    return LidarReturns(spec, t_ns, scan, angle, rng_m, flight.scenario_name)
