"""``vtolpose probe {imu,gps,camera}``: the first thing to run when a sensor is plugged in.

Talks to one device for a few seconds and prints what it says — identity, measured rate, the
first samples as CSV, and the packet statistics — so a technician can tell a wrong port, baud
rate, model range or counter setting from a working sensor without starting the estimator.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import TYPE_CHECKING

from vtolpose.service.commands.common import add_config_options, config_from

if TYPE_CHECKING:
    from vtolpose.config.sections import Sections
    from vtolpose.drivers.gps.common import GpsReading
    from vtolpose.drivers.imu.crossbow_serial import CrossbowConfig, ImuReading

COUNTER_AGREEMENT = 0.1  # implied tick within 10 % of the configured one counts as consistent


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "probe",
        help="field check of one sensor: identity, rate, first samples, packet statistics",
        description="Open one sensor for a few seconds and print what it says.\n\n"
        "Examples:\n"
        "  vtolpose probe imu --port /dev/ttyUSB0 --seconds 5\n"
        "  vtolpose probe gps --port /dev/ttyUSB1 --baud 9600\n"
        "  vtolpose probe gps --type mavlink --port udpin:0.0.0.0:14550\n"
        "  vtolpose probe camera --type opencv --port 0\n\n"
        "Settings not given come from the configuration (sensors.*). Exit status 0 when data arrived.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("sensor", choices=("imu", "gps", "camera"))
    p.add_argument("--port", help="serial port (imu, NMEA gps), pymavlink connection string (MAVLink gps), "
                                  "camera device (OpenCV index/path, libdc1394 GUID in hex)")
    p.add_argument("--baud", type=int, help="serial baud rate")
    p.add_argument("--type", dest="kind", help="gps: nmea | mavlink; camera: dc1394 | opencv (default: configuration)")
    p.add_argument("--seconds", type=float, default=5.0, help="how long to listen (default 5)")
    p.add_argument("--samples", type=int, default=5, help="how many first samples to print (default 5)")
    add_config_options(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from vtolpose.service.runtime.wiring import config_sections

    sections = config_sections(config_from(args))
    return {"imu": _probe_imu, "gps": _probe_gps, "camera": _probe_camera}[args.sensor](args, sections)


def _failed(sensor: str, message: object) -> int:
    print(f"probe {sensor}: FAILED: {message}", file=sys.stderr)
    return 1


def _rate(t_ns: list[int]) -> str:
    if len(t_ns) < 2:
        return f"{len(t_ns)} sample(s): too few for a rate"
    span = (t_ns[-1] - t_ns[0]) * 1e-9
    return f"{(len(t_ns) - 1) / span:.2f} Hz over {span:.2f} s ({len(t_ns)} samples)"


def _probe_imu(args: argparse.Namespace, sections: Sections) -> int:
    from vtolpose.drivers.imu.crossbow_serial import CrossbowConfig, CrossbowImu
    from vtolpose.drivers.links.serial_link import LINK_ERRORS, DeviceError

    conf = CrossbowConfig.from_section(sections.sensors, args.port, args.baud)
    print(f"probe imu: Crossbow IMU400CC on {conf.port} at {conf.baud} baud, {args.seconds:g} s")
    imu = CrossbowImu(conf)
    try:
        identity = imu.open()
    except (DeviceError, *LINK_ERRORS) as exc:
        return _failed("imu", exc)
    print(f"identity: {identity.describe()}")
    readings: list[ImuReading] = []
    end = time.monotonic() + args.seconds
    try:
        while time.monotonic() < end:
            readings += imu.read(min(0.05, max(0.0, end - time.monotonic())))
    finally:
        imu.close()
    print(f"first {min(args.samples, len(readings))} samples (sensor axes; t from the first sample):")
    print("t [s],gyro_x [rad/s],gyro_y [rad/s],gyro_z [rad/s],accel_x [m/s^2],accel_y [m/s^2],accel_z [m/s^2],"
          "temperature [C],counter")
    for r in readings[: args.samples]:
        values = ",".join(f"{v:.6f}" for v in (*r.gyro, *r.accel))
        print(f"{(r.t_ns - readings[0].t_ns) * 1e-9:.6f},{values},{r.temperature_c:.2f},{r.counter}")
    print(f"rate: {_rate([r.t_ns for r in readings])} (nominal {sections.sensors.imu.rate_hz:g} Hz)")
    counts = imu.counts()
    print("packets: " + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in counts.items()))
    print(_counter_report(readings, conf))
    return 0 if readings else _failed("imu", "no valid packet arrived; " + imu.status)


def _counter_report(readings: list[ImuReading], conf: CrossbowConfig) -> str:
    """Which tick length each count direction implies, against the configured (unconfirmed) one."""
    if len(readings) < 3:
        return "time counter: too few packets to check"
    import numpy as np

    counters = np.array([r.counter for r in readings], dtype=np.int64)
    dt = float(np.median(np.diff([r.t_ns for r in readings]))) * 1e-9
    up = float(np.median(np.diff(counters) % 65536))
    down = float(np.median(-np.diff(counters) % 65536))
    if up == 0 or down == 0:
        return "time counter: does not change between packets"
    tick_up, tick_down = dt / up, dt / down
    configured = conf.counter.tick_s
    mine, other = (tick_down, tick_up) if conf.counter.counts_down else (tick_up, tick_down)
    direction = "down" if conf.counter.counts_down else "up"
    if abs(mine / configured - 1.0) <= COUNTER_AGREEMENT:
        verdict = "consistent with the configuration"
    elif abs(other / configured - 1.0) <= COUNTER_AGREEMENT:
        verdict = "the count direction looks wrong: check sensors.imu.counter_direction"
    else:
        verdict = "neither matches: check sensors.imu.counter_tick_s and counter_direction"
    return (f"time counter: {up:.0f} ticks/packet counting up ({tick_up * 1e6:.4f} us/tick) or {down:.0f} counting "
            f"down ({tick_down * 1e6:.4f} us/tick) per {dt * 1e3:.2f} ms; configured {configured * 1e6:.4f} us "
            f"counting {direction}: {verdict}")


def _probe_gps(args: argparse.Namespace, sections: Sections) -> int:
    from vtolpose.drivers.links.serial_link import LINK_ERRORS

    kind = args.kind or sections.sensors.gps.type
    if kind == "nmea":
        from vtolpose.drivers.gps.nmea import NmeaConfig, NmeaGps

        conf = NmeaConfig.from_section(sections.sensors, args.port, args.baud)
        print(f"probe gps: NMEA on {conf.port} at {conf.baud} baud, {args.seconds:g} s")
        gps = NmeaGps(conf)
    elif kind == "mavlink":
        from vtolpose.drivers.gps.mavlink_gps import MavlinkGps, MavlinkGpsConfig

        conf = MavlinkGpsConfig.from_section(sections.sensors.gps, sections.vehicle.system_id, args.port)
        print(f"probe gps: MAVLink GPS_RAW_INT on {conf.url}, {args.seconds:g} s")
        gps = MavlinkGps(conf)
    else:
        return _failed("gps", f"gps type {kind!r}: use --type nmea or --type mavlink")
    try:
        gps.open()
    except LINK_ERRORS as exc:
        return _failed("gps", exc)
    fixes: list[GpsReading] = []
    end = time.monotonic() + args.seconds
    try:
        while time.monotonic() < end:
            fixes += gps.read(min(0.05, max(0.0, end - time.monotonic())))
    finally:
        gps.close()
    if kind == "nmea":
        seen = ", ".join(f"{k} {v}" for k, v in sorted(gps.sentence_types.items())) or "none"
        print(f"sentences: {seen}")
    print(f"first {min(args.samples, len(fixes))} fixes (NED around origin {gps.local.origin}):")
    print("t [s],lat [deg],lon [deg],alt [m],n [m],e [m],d [m],sigma_h [m],sigma_v [m],sigma from,satellites")
    for r in fixes[: args.samples]:
        n, e, d = r.fix.p_ned
        print(f"{(r.fix.t_ns - fixes[0].fix.t_ns) * 1e-9:.3f},{r.lat_deg:.8f},{r.lon_deg:.8f},{r.alt_m:.3f},"
              f"{n:.3f},{e:.3f},{d:.3f},{r.fix.sigma_h:.3f},{r.fix.sigma_v:.3f},{r.sigma_source},{r.satellites}")
    print(f"rate: {_rate([r.fix.t_ns for r in fixes])}")
    print("counts: " + (", ".join(f"{k.replace('_', ' ')} {v}" for k, v in sorted(gps.counts.items())) or "nothing"))
    return 0 if fixes else _failed("gps", "no usable fix arrived; " + gps.status)


def _probe_camera(args: argparse.Namespace, sections: Sections) -> int:
    from vtolpose.drivers.camera.common import CameraUnavailable
    from vtolpose.drivers.camera.select import camera_from_config

    kind = args.kind or sections.sensors.camera.type
    try:
        if kind == "dc1394":
            from vtolpose.drivers.camera.dc1394 import list_cameras

            found = list_cameras()
            print("IIDC cameras: " + ("; ".join(c.describe() for c in found) or "none"))
        camera = camera_from_config(sections.sensors.camera, kind, args.port)
        print(f"probe camera: {camera.open()}, {args.seconds:g} s")
    except (CameraUnavailable, ValueError) as exc:
        return _failed("camera", exc)
    frames = []
    end = time.monotonic() + args.seconds
    try:
        while time.monotonic() < end:
            frame = camera.read(min(0.5, max(0.0, end - time.monotonic())))
            if frame is not None:
                frames.append((frame.t_ns, frame.seq, frame.image.shape, float(frame.image.mean())))
            elif getattr(camera, "ended", False):
                break
    finally:
        camera.close()
    print(f"first {min(args.samples, len(frames))} frames:")
    print("t [s],seq,width,height,mean intensity")
    for t_ns, seq, shape, mean in frames[: args.samples]:
        print(f"{(t_ns - frames[0][0]) * 1e-9:.4f},{seq},{shape[1]},{shape[0]},{mean:.1f}")
    print(f"rate: {_rate([f[0] for f in frames])}")
    return 0 if frames else _failed("camera", "no frame arrived")
