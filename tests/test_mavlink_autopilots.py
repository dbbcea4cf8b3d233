"""ODOMETRY as PX4 and ArduPilot take it, checked with their receiving rules (tests/autopilot_rules.py) on
messages that real pymavlink peers received over loopback: a run from an unknown heading to an aligned
one never offers a default-configured autopilot a pose vtolpose knows is unusable; the rates hold; the
TIMESYNC round trip maps ``time_usec`` onto the autopilot's clock; an injected GPS jump that resets the
filter reaches the ground station as STATUSTEXT."""

import asyncio
import math
import socket
import threading
import time

import numpy as np
import pytest

from vtolpose.config import load_config
from vtolpose.config.mavlink_settings import EndpointSpec
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.service.cli import main
from vtolpose.service.outputs.mavlink_output import COMPONENT_ID, Endpoint, MavlinkOutput, mavutil
from vtolpose.service.outputs.mavlink_odometry import PROFILES, odometry_quality
from vtolpose.service.runtime.daemon import build_runtime, serve
from vtolpose.service.runtime.sources import ReplayClock, ReplaySource
from vtolpose.service.runtime.status import pose_problem

from autopilot_rules import (
    ARDUPILOT_MIN_INTERVAL_US, ardupilot_errors_known, ardupilot_fuses, px4_fused_parts, px4_variances_consistent,
)
from runtime_helpers import PoseList
from test_mavlink_out import free_udp_port, make_pose

mav = mavutil.mavlink


class Collector:
    """A UDP peer that keeps every MAVLink message it receives (a thread; a large socket buffer)."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.messages: list = []
        self._decoder = mav.MAVLink(None)
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop:
            try:
                data = self.sock.recv(65535)
            except socket.timeout:
                continue
            self.messages += self._decoder.parse_buffer(data) or []

    def of(self, kind: str) -> list:
        return [m for m in self.messages if m.get_type() == kind]

    def close(self) -> None:
        time.sleep(0.2)
        self._stop = True
        self._thread.join()
        self.sock.close()


def spec(name: str, port: int, rate_hz: float, role: str = "autopilot") -> EndpointSpec:
    return EndpointSpec(name, f"udpout:127.0.0.1:{port}", role, rate_hz, None, False, name)


@pytest.fixture(scope="module")
def book(flight_folder) -> Dataset:
    """A flight whose heading vtolpose must find in motion (about 12 s in): conftest's book, written."""
    return Dataset.open(flight_folder("book", 45.0, 3))


def test_from_unknown_to_aligned_heading_no_autopilot_fuses_an_unusable_pose(book):
    cfg = load_config(None, {"estimator": {"heading": {"source": "gps"}}})
    px4_peer, ardupilot_peer = Collector(), Collector()
    out = MavlinkOutput([
        Endpoint(spec("px4", px4_peer.port, 50.0), None, PROFILES["px4"], 1, COMPONENT_ID),
        Endpoint(spec("ardupilot", ardupilot_peer.port, 30.0), None, PROFILES["ardupilot"], 1, COMPONENT_ID),
    ])
    poses = PoseList()
    runtime = build_runtime(cfg, book.calibration)
    runtime.outputs += [out, poses]
    source = ReplaySource(book, ["imu", "gps"], ReplayClock(4.0))
    try:
        asyncio.run(serve(runtime, [source], handle_signals=False))
    finally:
        px4_peer.close()
        ardupilot_peer.close()
    by_time = {p.t_ns: p for p in poses.poses}
    for name, peer, rate, fuses in (
        ("px4", px4_peer, 50.0, lambda m: bool(px4_fused_parts(m, ev_qmin=0))),
        ("ardupilot", ardupilot_peer, 30.0, lambda m: ardupilot_fuses(m, qual_min=0)),
    ):
        odometry = peer.of("ODOMETRY")
        assert len(odometry) > 0.9 * rate * 40, name
        unusable = fused = 0
        for msg in odometry:
            pose = by_time[msg.time_usec * 1000]
            assert msg.quality == odometry_quality(pose), name
            if pose_problem(pose) is not None:  # vtolpose's own status says: do not use
                unusable += 1
                assert msg.quality == -1 and not fuses(msg), (name, pose_problem(pose))
            else:
                fused += fuses(msg)
            assert px4_variances_consistent(msg) and ardupilot_errors_known(msg), name
        assert unusable > 0.9 * rate * 10 and fused > 0.9 * rate * 30, (name, unusable, fused)  # both sides of alignment
        t = np.array([m.time_usec for m in odometry])
        achieved = (len(t) - 1) / ((t[-1] - t[0]) * 1e-6)
        print(f"{name}: {len(odometry)} ODOMETRY at {achieved:.2f} Hz (configured {rate:g}), {unusable} unusable "
              f"(none fused), {fused} fused")
        assert achieved == pytest.approx(rate, rel=0.02), name
    assert np.diff([m.time_usec for m in ardupilot_peer.of("ODOMETRY")]).min() >= ARDUPILOT_MIN_INTERVAL_US
    aligned_at = min(p.t_ns for p in poses.poses if p.heading_aligned)
    texts = [m.text for m in px4_peer.of("STATUSTEXT")]
    assert "vtolpose: heading aligned, pose usable" in texts
    assert runtime.status_document()["pose_problem"] is None and aligned_at > poses.poses[0].t_ns


def test_timesync_round_trip_maps_time_usec_onto_the_autopilots_clock():
    """A peer that times as PX4 does (mavlink_timesync / Timesync::update): it sends requests with its clock in
    ``ts1``; from the answers it estimates the offset between its clock and ours, and maps each ODOMETRY's
    ``time_usec`` onto its clock. The poses here are stamped on a clock of their own (a replay's), 5 s from
    the host's: what matters is that the answers and ``time_usec`` are on the same one."""
    autopilot_clock = lambda: time.monotonic_ns() + 7_000_000_000  # noqa: E731  (its boot clock)
    sensor_offset = -5_000_000_000
    port = free_udp_port()
    px4 = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    px4.bind(("127.0.0.1", port))
    px4.settimeout(0.05)
    out = MavlinkOutput([Endpoint(spec("fc", port, 50.0), None, PROFILES["px4"], 1, COMPONENT_ID)])
    out.open()
    enc, dec = mav.MAVLink(None, 1, 1), mav.MAVLink(None)
    offsets, rtts, arrivals, unanswered = [], [], [], []
    listening = True

    def listen() -> None:  # the autopilot's receiving side: every message with its arrival on its clock
        while listening:
            try:
                data = px4.recv(65535)
            except socket.timeout:
                continue
            now = autopilot_clock()
            for msg in dec.parse_buffer(data) or []:
                if msg.get_type() == "TIMESYNC" and msg.tc1 > 0:
                    rtts.append((now - msg.ts1) * 1e-6)
                    offsets.append((msg.ts1 + now - 2 * msg.tc1) / 2)  # theirs minus ours, as PX4 computes it
                elif msg.get_type() == "ODOMETRY":
                    arrivals.append((msg.time_usec, now))

    async def run() -> None:
        stop = asyncio.Event()
        task = asyncio.create_task(out.serve(stop))
        out.heartbeat()  # from our socket: the autopilot learns where we are
        vtolpose = ("127.0.0.1", out.endpoints[0].transport.sock.getsockname()[1])
        px4.sendto(mav.MAVLink_timesync_message(0, autopilot_clock()).pack(enc), vtolpose)  # before any pose
        await asyncio.sleep(0.05)
        unanswered.append(out.link_stats()["endpoints"]["fc"].get("timesync_unanswered_no_pose_yet", 0))
        for k in range(250):  # two seconds of 125 Hz poses, a request every 40 ms
            out.publish(make_pose(t_ns=time.monotonic_ns() + sensor_offset))
            if k % 5 == 0:
                px4.sendto(mav.MAVLink_timesync_message(0, autopilot_clock()).pack(enc), vtolpose)
            await asyncio.sleep(0.008)
        await asyncio.sleep(0.1)
        stop.set()
        await task

    listener = threading.Thread(target=listen)
    listener.start()
    try:
        asyncio.run(run())
    finally:
        listening = False
        listener.join()
        out.close()
        px4.close()
    offset = np.median(offsets)
    mapped_ms = np.array([(t_usec * 1000 + offset - now) * 1e-6 for t_usec, now in arrivals])
    print(f"TIMESYNC: {len(offsets)} answers, round trip median {np.median(rtts):.2f} ms (max {max(rtts):.2f}), offset "
          f"{offset * 1e-9:.4f} s, time_usec mapped within {np.median(np.abs(mapped_ms)):.2f} ms (median)")
    assert unanswered == [1]  # no pose yet: no clock to answer with
    assert len(offsets) == 50 and np.median(rtts) < 10.0  # PX4 only uses samples under 10 ms
    assert abs(offset * 1e-9 - (7.0 - (-5.0))) < 0.005  # the offset between the two clocks: 12 s
    assert len(mapped_ms) > 100 and abs(np.median(mapped_ms)) < 3.0  # time_usec lands where the pose was
    assert out.link_stats()["endpoints"]["fc"]["timesync_answered"] == len(offsets)


def test_a_gps_jump_reset_reaches_the_ground_station_as_statustext(tmp_path, capsys):
    root = tmp_path / "landfill"
    write_flight(simulate_flight("landfill", 70.0, 3), root)
    fc, gcs = Collector(), Collector()
    endpoints = f"[{{name: gcs, url: 'udpout:127.0.0.1:{gcs.port}', role: ground_station, rate_hz: 2}}]"
    try:
        code = main(["run", "--replay", str(root), "--speed", "0", "--fault", "gps-jump:30:20,0,0:15",
                     "--mavlink", f"udpout:127.0.0.1:{fc.port}", "--set", "outputs.mavlink.autopilot=ardupilot",
                     "--set", f"outputs.mavlink.endpoints={endpoints}"])
    finally:
        fc.close()
        gcs.close()
    assert code == 0, capsys.readouterr().err
    for peer in (fc, gcs):
        texts = [m.text for m in peer.of("STATUSTEXT")]
        resets = [t for t in texts if "filter reset" in t and "gps_rejected" in t]
        assert resets, texts
        warning = next(m for m in peer.of("STATUSTEXT") if m.text == resets[0])
        assert warning.severity == mav.MAV_SEVERITY_WARNING
    assert {m.frame_id for m in fc.of("ODOMETRY")} == {mav.MAV_FRAME_LOCAL_FRD}  # the autopilot's profile
    assert {m.frame_id for m in gcs.of("ODOMETRY")} == {mav.MAV_FRAME_LOCAL_NED}
    resets_seen = {m.reset_counter for m in fc.of("ODOMETRY")}
    assert len(resets_seen) >= 2  # reset_counter moved on at the reset


def yaw_deg(msg) -> float:
    w, x, y, z = msg.q
    return math.degrees(math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


def test_ardupilot_sees_no_yaw_step_when_a_gps_reset_places_the_heading_again(tmp_path, capsys):
    """A heading found from GPS, then a GPS jump that resets the filter and has the heading searched for
    again: the estimator's yaw steps by 10-26° at its resets (seen without the absorbing frame); what
    ArduPilot receives goes on smoothly, and its reset_counter moves at each reset."""
    root = tmp_path / "landfill"
    write_flight(simulate_flight("landfill", 70.0, 3), root)
    fc = Collector()
    try:
        code = main(["run", "--replay", str(root), "--speed", "0", "--fault", "gps-jump:30:20,0,0:15",
                     "--mavlink", f"udpout:127.0.0.1:{fc.port}", "--set", "outputs.mavlink.autopilot=ardupilot",
                     "--set", "estimator.heading.source=gps"])
    finally:
        fc.close()
    assert code == 0, capsys.readouterr().err
    odometry = [m for m in fc.of("ODOMETRY") if all(map(math.isfinite, m.q))]
    at_resets = [abs((yaw_deg(b) - yaw_deg(a) + 180.0) % 360.0 - 180.0)
                 for a, b in zip(odometry, odometry[1:]) if a.reset_counter != b.reset_counter]
    print(f"{len(odometry)} ODOMETRY, yaw change at the {len(at_resets)} reset steps: {[round(d, 2) for d in at_resets]} deg")
    assert len(at_resets) >= 3 and max(at_resets) < 1.0
