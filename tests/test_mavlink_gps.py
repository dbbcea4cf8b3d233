"""MAVLink GPS driver: a pymavlink peer sends GPS_RAW_INT over UDP loopback."""

from __future__ import annotations

import math
import socket
import time

import numpy as np
import pymap3d
import pytest

from vtolpose.drivers.gps.mavlink_gps import MavlinkGps, MavlinkGpsConfig

ORIGIN = (58.4, 15.6, 100.0)


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_gps_raw_int_becomes_local_ned_fixes():
    from pymavlink import mavutil

    port = free_udp_port()
    gps = MavlinkGps(MavlinkGpsConfig(f"udpin:127.0.0.1:{port}", uere_m=4.0, origin=ORIGIN, system_id=1))
    gps.open()
    autopilot = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    other = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=2, source_component=1)
    lat = [58.4 + 1e-5 * i for i in range(6)]

    def send(conn, i, fix_type=3, eph=90, epv=140, h_acc=0, v_acc=0, time_usec=None):
        conn.mav.gps_raw_int_send(time_usec if time_usec is not None else 1_000_000 + 200_000 * i, fix_type,
                                  round(lat[i] * 1e7), round(15.6e7), 100_000 + 500 * i, eph, epv, 0, 0, 9,
                                  alt_ellipsoid=0, h_acc=h_acc, v_acc=v_acc)

    try:
        send(autopilot, 0)
        send(autopilot, 1, fix_type=2)                      # 2-D fix only: skipped
        send(autopilot, 2)
        send(autopilot, 2)                                  # the same receiver epoch again: skipped
        send(autopilot, 3, eph=65535, epv=65535)            # no accuracy at all: skipped
        send(autopilot, 4, h_acc=700, v_acc=1200)           # the receiver's own accuracy wins over DOP
        send(other, 5)                                      # another vehicle: ignored
        readings, deadline = [], time.monotonic() + 2.0
        while len(readings) < 3 and time.monotonic() < deadline:
            readings += gps.read(0.1)
        readings += gps.read(0.2)
    finally:
        gps.close()
        autopilot.close()
        other.close()
    assert [round((r.lat_deg - 58.4) / 1e-5) for r in readings] == [0, 2, 4]
    expected = np.column_stack(pymap3d.geodetic2ned(np.array(lat)[[0, 2, 4]], 15.6, np.array([100.0, 101.0, 102.0]), *ORIGIN))
    assert np.allclose([r.fix.p_ned for r in readings], expected, atol=1e-3)
    assert readings[0].sigma_source == "DOP"
    assert readings[0].fix.sigma_h == pytest.approx(0.9 * 4.0 / math.sqrt(2))
    assert readings[0].fix.sigma_v == pytest.approx(1.4 * 4.0)
    assert readings[2].sigma_source == "accuracy"
    assert readings[2].fix.sigma_h == pytest.approx(0.7 / math.sqrt(2)) and readings[2].fix.sigma_v == pytest.approx(1.2)
    assert all(b.fix.t_ns > a.fix.t_ns for a, b in zip(readings, readings[1:]))
    assert gps.counts["no_fix"] == 1 and gps.counts["duplicate"] == 1 and gps.counts["no_accuracy"] == 1
    assert gps.counts["other_system"] == 1 and gps.counts["fixes"] == 3


def test_read_without_connection_does_not_raise():
    gps = MavlinkGps(MavlinkGpsConfig("udpin:127.0.0.1:1"))
    assert gps.read(0.01) == [] and gps.status == "closed"
