"""Live sources for ``vtolpose run``: the hardware drivers (``sensors.*``) as runtime sources.

Each blocking driver is read on its own thread (:class:`~vtolpose.service.runtime.sources.ThreadedSource`). A
device that cannot be opened at start is retried by its driver (with back-off) while the
others run; only a camera marked ``required`` stops the start. The autopilot's GPS can share
the MAVLink output link (``sensors.gps.mavlink_url`` equal to ``outputs.mavlink.url``): its
``GPS_RAW_INT`` messages are then taken from that link, under that link's signing settings, rather than
a second connection (config/mavlink_settings.py refuses GPS signing settings that differ from the link's).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any, AsyncIterator, Callable

from vtolpose.config.sections import Sections
from vtolpose.service.runtime.loop import Runtime
from vtolpose.service.runtime.sources import ThreadedSource

log = logging.getLogger(__name__)

Origin = tuple[float, float, float] | None


@dataclass
class LiveSources:
    sources: list[AsyncIterator] = field(default_factory=list)
    origin: Callable[[], Origin] = lambda: None
    notes: list[str] = field(default_factory=list)


def _open(name: str, driver: Any, notes: list[str]) -> None:
    try:
        described = driver.open()
        log.info("%s: %s", name, described.describe() if hasattr(described, "describe") else described or "open")
    except (OSError, RuntimeError) as exc:  # DeviceError and SerialException are among these
        notes.append(f"{name}: {exc}; retrying in the background")
        log.warning(notes[-1])


def live_sources(sections: Sections, runtime: Runtime, recorder: Any | None = None) -> LiveSources:
    """Sources for the devices in ``sensors``; the runtime's MAVLink output may carry the GPS.

    ``recorder`` (a :class:`~vtolpose.service.outputs.recorder.FlightRecorder`) sees every raw reading on the
    device threads, before the estimator: the recording replays to the same trajectory.
    """
    from vtolpose.drivers.imu.crossbow_serial import CrossbowConfig, CrossbowImu

    sensors = sections.sensors
    live = LiveSources()
    imu = CrossbowImu(CrossbowConfig.from_section(sensors))
    _open("IMU", imu, live.notes)
    imu_tap = None if recorder is None else (lambda r: recorder.record_imu(r.t_ns, r.gyro, r.accel))
    live.sources.append(ThreadedSource("imu", imu, lambda reading: reading.sample, tap=imu_tap))

    def gps_tap(gps: Any) -> Callable[[Any], None] | None:
        if recorder is None:
            return None
        return lambda r: recorder.record_gps(r.fix.t_ns, r.lat_deg, r.lon_deg, r.alt_m, r.fix.sigma_h, r.fix.sigma_v,
                                             origin=gps.local.origin)

    gps_type = sensors.gps.type
    if gps_type == "nmea":
        from vtolpose.drivers.gps.nmea import NmeaConfig, NmeaGps

        gps = NmeaGps(NmeaConfig.from_section(sensors))
        _open("GPS", gps, live.notes)
        live.sources.append(ThreadedSource("gps", gps, lambda reading: reading.fix, tap=gps_tap(gps)))
        live.origin = lambda: gps.local.origin
    elif gps_type == "mavlink":
        from vtolpose.drivers.gps.mavlink_gps import MavlinkGps, MavlinkGpsConfig

        gps = MavlinkGps(MavlinkGpsConfig.from_section(sensors.gps, sections.vehicle.system_id))
        live.origin = lambda: gps.local.origin
        link = next((o for o in runtime.outputs if o.name == "mavlink"), None)
        if link is not None and link.url == sensors.gps.mavlink_url:
            tap = gps_tap(gps)

            def on_gps_raw(msg: Any) -> None:
                reading = gps.convert(msg, time.monotonic_ns())  # the driver's conversion, on our link
                if reading is not None:
                    if tap is not None:
                        tap(reading)
                    runtime.handle(reading.fix)

            link.handlers["GPS_RAW_INT"] = on_gps_raw
        else:
            _open("GPS (MAVLink)", gps, live.notes)
            live.sources.append(ThreadedSource("gps", gps, lambda reading: reading.fix, tap=gps_tap(gps)))

    if sensors.camera.type != "none":
        if runtime.camera_processor is None:
            live.notes.append("camera: no feature extractor is wired into the runtime; frames are not read")
            log.warning(live.notes[-1])
        else:
            from vtolpose.drivers.camera.common import CameraUnavailable
            from vtolpose.drivers.camera.select import camera_from_config

            camera = camera_from_config(sensors.camera)
            try:
                log.info("camera: %s", camera.open())
                camera_tap = None if recorder is None else recorder.record_camera
                live.sources.append(ThreadedSource("camera", camera, lambda frame: frame, read_timeout_s=0.5,
                                                   tap=camera_tap))
            except CameraUnavailable as exc:
                if sensors.camera.required:
                    raise
                live.notes.append(f"camera: {exc}; running without images")
                log.warning(live.notes[-1])
    return live
