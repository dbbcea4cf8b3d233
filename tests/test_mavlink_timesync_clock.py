"""TIMESYNC answered on the clock ``time_usec`` is stamped on, over UDP and over a serial link (a pseudo-
terminal), with a peer that times as PX4 does: requests carry its clock in ``ts1``, round trips over 10 ms are
thrown away, the offset is the median of the rest, and each ODOMETRY's ``time_usec`` is mapped through it.
The poses leave ``AGE_MS`` after their IMU sample, as a live run's do: the mapped stamps must land on the
sample's own time (not ``AGE_MS`` later), and the status must report that age."""

from __future__ import annotations

import asyncio
import os
import pty
import select
import socket
import threading
import time

import numpy as np
import pytest

from vtolpose.service.outputs.mavlink_output import MavlinkOutput, SensorClock, mavutil

from test_mavlink_out import endpoint, make_pose

mav = mavutil.mavlink
AGE_MS = 25.0
AUTOPILOT_OFFSET_NS = 7_000_000_000  # the autopilot's boot clock against our monotonic clock
PX4_MAX_RTT_MS = 10.0


def autopilot_clock() -> int:
    return time.monotonic_ns() + AUTOPILOT_OFFSET_NS


class Px4Peer:
    """The autopilot side: sends requests through ``write``, reads what ``read`` returns, on its own thread."""

    def __init__(self, write, read) -> None:
        self.write, self.read = write, read
        self.enc, self.dec = mav.MAVLink(None, 1, 1), mav.MAVLink(None)
        self.rtts_ms: list[float] = []
        self.offsets_ns: list[float] = []
        self.odometry: list[tuple[int, int]] = []  # (time_usec, arrival on the autopilot's clock)
        self.running = True
        self.thread = threading.Thread(target=self._listen, daemon=True)
        self.thread.start()

    def request(self) -> None:
        self.write(mav.MAVLink_timesync_message(0, autopilot_clock()).pack(self.enc))

    def _listen(self) -> None:
        while self.running:
            data = self.read()
            now = autopilot_clock()
            for msg in self.dec.parse_buffer(data) or [] if data else []:
                if msg.get_type() == "TIMESYNC" and msg.tc1 > 0:
                    rtt_ms = (now - msg.ts1) * 1e-6
                    self.rtts_ms.append(rtt_ms)
                    if rtt_ms < PX4_MAX_RTT_MS:  # PX4 keeps only these
                        self.offsets_ns.append((msg.ts1 + now - 2 * msg.tc1) / 2)
                elif msg.get_type() == "ODOMETRY":
                    self.odometry.append((msg.time_usec, now))

    def stop(self) -> None:
        self.running = False
        self.thread.join()

    def mapped_error_ms(self) -> np.ndarray:
        """Each ODOMETRY's time_usec through the offset, against its sample's true time on the autopilot's clock."""
        offset = np.median(self.offsets_ns)
        return np.array([(t_usec * 1000 + offset - (t_usec * 1000 + AUTOPILOT_OFFSET_NS)) * 1e-6
                         for t_usec, _ in self.odometry])


async def fly(out: MavlinkOutput, peer: Px4Peer, seconds: float = 2.0) -> None:
    """125 Hz poses stamped AGE_MS before they are published; a TIMESYNC request every 40 ms."""
    stop = asyncio.Event()
    task = asyncio.create_task(out.serve(stop))
    for k in range(int(seconds * 125)):
        out.publish(make_pose(t_ns=time.monotonic_ns() - int(AGE_MS * 1e6)))
        if k % 5 == 0:
            peer.request()
        await asyncio.sleep(0.008)
    await asyncio.sleep(0.1)
    stop.set()
    await task


def check(peer: Px4Peer, out: MavlinkOutput) -> None:
    """Most round trips under PX4's 10 ms, and the mapped stamps within 2 ms of the sample's time (PX4 splits the
    round trip evenly, so a request that waited on one side and not the other would shift them by half the wait)."""
    errors = peer.mapped_error_ms()
    print(f"{len(peer.rtts_ms)} answers, round trip median {np.median(peer.rtts_ms):.2f} ms (max {max(peer.rtts_ms):.2f}), "
          f"{len(peer.offsets_ns)} under 10 ms; time_usec mapped {np.median(errors):+.2f} ms off the sample's time; "
          f"pose age {out.link_stats()['pose_age_ms']}")
    assert len(peer.offsets_ns) >= 0.9 * len(peer.rtts_ms) and len(peer.offsets_ns) >= 20
    assert abs(np.median(errors)) < 2.0  # on the sample's own time, not AGE_MS late
    stats = out.link_stats()
    assert stats["pose_age_ms"]["p50"] == pytest.approx(AGE_MS, abs=3.0)
    assert stats["delay_to_configure_ms"] == pytest.approx(AGE_MS, abs=4.0)


def test_udp_answers_on_the_imu_clock_and_the_stamps_map_exactly():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.05)
    out = MavlinkOutput([endpoint(f"udpout:127.0.0.1:{sock.getsockname()[1]}", autopilot="px4")], "px4",
                        clock=SensorClock(now=time.monotonic_ns))
    out.open()
    out.heartbeat()  # from our socket: the autopilot learns where we are
    ours = ("127.0.0.1", out.endpoints[0].transport.sock.getsockname()[1])

    def read() -> bytes:
        try:
            return sock.recv(65535)
        except socket.timeout:
            return b""

    peer = Px4Peer(lambda data: sock.sendto(data, ours), read)
    try:
        asyncio.run(fly(out, peer))
    finally:
        peer.stop()
        out.close()
        sock.close()
    check(peer, out)


def test_a_serial_link_converges_within_px4s_round_trip_limit():
    master, slave = pty.openpty()
    out = MavlinkOutput([endpoint(f"{os.ttyname(slave)},921600", autopilot="px4")], "px4",
                        clock=SensorClock(now=time.monotonic_ns))
    out.open()

    def read() -> bytes:
        ready, _, _ = select.select([master], [], [], 0.05)
        return os.read(master, 65536) if ready else b""

    peer = Px4Peer(lambda data: os.write(master, data), read)
    try:
        asyncio.run(fly(out, peer, seconds=3.0))
    finally:
        peer.stop()
        out.close()
        os.close(master)
        os.close(slave)
    # A serial link is read when its descriptor is readable, as a UDP socket is: a request waits for no poll on
    # the way in, so the round trip splits evenly and the stamps map as closely as over UDP.
    check(peer, out)
