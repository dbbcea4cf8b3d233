"""Typed, read-only sections of the validated configuration, for the drivers and outputs.

Each field is named like the last part of its key (``sensors.gps.uere_m`` is ``GpsSection.uere_m``)
and :func:`build_section` fills a section from its key prefix by those names, so a section cannot
drift from the schema: a field without a key fails at start, and a test checks that every key
has a field or is one the estimator's options take (:data:`ESTIMATOR_PREFIXES`).
Lists become the tuples their fields declare (a matrix's rows too), so that a section shared by
several parts cannot be changed by one of them.
"""

from __future__ import annotations

import typing
from dataclasses import dataclass, fields, is_dataclass
from typing import Any, Mapping, TypeVar

__all__ = [
    "CameraSection", "ESTIMATOR_PREFIXES", "FoxgloveSection", "FusionSection", "GpsSection", "ImuSection",
    "MavlinkSection", "McapSection", "OutputsSection", "ReplaySection", "Ros2Section", "RunSection", "Sections",
    "SensorsSection", "SmoothingSection", "VehicleSection", "ZenohSection", "ZenohTlsSection", "build_section",
    "build_sections",
]

# Keys read by the estimator's options builder (service/runtime/wiring.py) from the flat values, not sections.
ESTIMATOR_PREFIXES = ("estimator.", "features.", "calibration.")

Vector3 = tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class VehicleSection:
    name: str
    system_id: int


@dataclass(frozen=True, slots=True)
class ImuSection:
    port: str
    baud: int
    rate_hz: float
    rate_range_dps: float
    accel_range_g: float
    counter_tick_s: float
    counter_direction: str  # up | down
    R_BI: tuple[Vector3, Vector3, Vector3]
    reply_timeout_s: float
    silence_timeout_s: float


@dataclass(frozen=True, slots=True)
class GpsSection:
    type: str  # nmea | mavlink | none
    port: str
    baud: int
    mavlink_url: str
    signing_key_file: str | None
    require_signing: bool
    uere_m: float
    origin: Vector3 | None
    silence_timeout_s: float


@dataclass(frozen=True, slots=True)
class CameraSection:
    type: str  # dc1394 | opencv | none
    device: str | None
    mode: str
    width: int
    height: int
    fps: float
    latency_s: float
    required: bool


@dataclass(frozen=True, slots=True)
class SensorsSection:
    reconnect_min_s: float
    reconnect_max_s: float
    imu: ImuSection
    gps: GpsSection
    camera: CameraSection


@dataclass(frozen=True, slots=True)
class FusionSection:
    delay_s: float
    max_pending: int
    max_imu_buffer: int
    camera_workers: int
    camera_process: bool
    update_thread: bool


@dataclass(frozen=True, slots=True)
class RunSection:
    calibration_file: str | None
    trajectory: str | None
    record_dir: str | None
    realtime_priority: int | None


@dataclass(frozen=True, slots=True)
class ReplaySection:
    sensors: tuple[str, ...]
    nees_rate_hz: float
    speed: float
    camera_workers: int
    camera_process: bool


@dataclass(frozen=True, slots=True)
class SmoothingSection:
    fixed_lag_s: float
    steps_per_sample: int
    max_window_s: float
    chunk_steps: int
    temp_dir: str | None


@dataclass(frozen=True, slots=True)
class MavlinkSection:
    enabled: bool
    autopilot: str  # px4 | ardupilot | generic
    url: str | None
    rate_hz: float | None
    component_id: int
    signing_key_file: str | None
    require_signing: bool
    endpoints: tuple[dict[str, Any], ...]  # each checked by config/mavlink_settings.py
    max_udp_peers: int
    udp_peer_timeout_s: float
    statustext_per_minute: int


@dataclass(frozen=True, slots=True)
class ZenohTlsSection:
    root_ca_certificate: str | None
    certificate: str | None
    private_key: str | None
    mutual: bool


@dataclass(frozen=True, slots=True)
class ZenohSection:
    enabled: bool
    mode: str  # peer | client
    listen: tuple[str, ...]
    connect: tuple[str, ...]
    multicast_scouting: bool
    config_file: str | None
    prefix: str | None
    history_s: float
    max_window_s: float
    max_queries_per_s: float
    max_pending_queries: int
    query_process: bool
    tls: ZenohTlsSection


@dataclass(frozen=True, slots=True)
class Ros2Section:
    enabled: bool
    domain_id: int
    namespace: str
    node_name: str
    odometry_topic: str
    tf_topic: str
    map_frame: str
    odom_frame: str | None
    base_frame: str
    stamp: str  # auto | estimator | system


@dataclass(frozen=True, slots=True)
class FoxgloveSection:
    enabled: bool
    host: str
    port: int
    rate_hz: float
    path_points: int


@dataclass(frozen=True, slots=True)
class McapSection:
    file: str | None


@dataclass(frozen=True, slots=True)
class OutputsSection:
    mavlink: MavlinkSection
    zenoh: ZenohSection
    ros2: Ros2Section
    foxglove: FoxgloveSection
    mcap: McapSection


@dataclass(frozen=True, slots=True)
class Sections:
    """Every section but the estimator's; the field names are the top-level keys."""

    vehicle: VehicleSection
    sensors: SensorsSection
    fusion: FusionSection
    run: RunSection
    replay: ReplaySection
    smoothing: SmoothingSection
    outputs: OutputsSection


S = TypeVar("S")


def _as_declared(value: Any, hint: Any) -> Any:
    """A list as the tuple its field declares, rows too when the items are declared tuples; anything else
    (a mapping in a list, say) as it is, so that a check's message shows it as it was written."""
    if not isinstance(value, list):
        return value
    declared = typing.get_args(hint)
    item = declared[0] if declared else None
    if typing.get_origin(item) is tuple:
        return tuple(_as_declared(v, item) for v in value)
    return tuple(value)


def build_section(cls: type[S], values: Mapping[str, Any], prefix: str) -> S:
    """``cls`` from the validated flat ``values`` under ``prefix``: a field takes the key named like it, a
    section-typed field the keys one level deeper. A field without a key is a KeyError naming the key."""
    hints = typing.get_type_hints(cls)
    given = {}
    for f in fields(cls):  # type: ignore[arg-type]
        key = f"{prefix}.{f.name}" if prefix else f.name
        kind = hints[f.name]
        given[f.name] = build_section(kind, values, key) if is_dataclass(kind) else _as_declared(values[key], kind)
    return cls(**given)


def build_sections(values: Mapping[str, Any]) -> Sections:
    """All sections from the flat values :func:`vtolpose.config.load_config` returns."""
    return build_section(Sections, values, "")
