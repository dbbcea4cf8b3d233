"""Serial and TCP MAVLink links are read when their descriptor is readable, as UDP sockets are, not on a timer:
a TIMESYNC request is answered within a fraction of a millisecond whenever it comes, the descriptor is followed
through a reconnection, and a flood still rests for its cooldown and is then read to the end, nothing that was
read lost. Real peers: a pseudo-terminal and a loopback TCP server."""

from __future__ import annotations

import asyncio
import os
import pty
import random
import select
import socket
import threading
import time
from typing import Callable

import numpy as np

from vtolpose.service.outputs import mavlink_output
from vtolpose.service.outputs.mavlink_output import MavlinkOutput, SensorClock, mavutil

from test_mavlink_out import endpoint

mav = mavutil.mavlink


def timesync_round_trips(write, read, count: int, answered) -> list[float]:
    """``count`` TIMESYNC requests at random moments (0-7 ms apart: any phase against a timer), each waited for."""
    enc, dec = mav.MAVLink(None, 1, 1), mav.MAVLink(None)
    rng = random.Random(7)
    trips = []
    for k in range(count):
        time.sleep(rng.uniform(0.0, 0.007))
        sent = time.monotonic_ns()
        write(mav.MAVLink_timesync_message(0, sent + k).pack(enc))
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            data = read()
            msgs = dec.parse_buffer(data) or [] if data else []
            if any(m.get_type() == "TIMESYNC" and m.ts1 == sent + k for m in msgs):
                trips.append((time.monotonic_ns() - sent) * 1e-6)
                answered.append(k)
                break
    return trips


def serve_beside(out: MavlinkOutput, peer: threading.Thread, *closing: Callable[[], None]) -> None:
    """Serve ``out`` on an event loop while ``peer`` (started here) runs; then close it, and ``closing`` after it."""

    async def serve() -> None:
        stop = asyncio.Event()
        task = asyncio.create_task(out.serve(stop))
        while peer.is_alive():
            await asyncio.sleep(0.01)
        stop.set()
        await task

    try:
        peer.start()
        asyncio.run(serve())
    finally:
        out.close()
        for close in closing:
            close()


def test_a_serial_link_is_read_when_data_comes_not_when_a_timer_fires(monkeypatch):
    # The link's service timer set to a minute: only readability can get the requests read.
    monkeypatch.setattr(mavlink_output, "STREAM_SERVICE_S", 60.0)
    master, slave = pty.openpty()
    out = MavlinkOutput([endpoint(f"{os.ttyname(slave)},921600")], clock=SensorClock(now=time.monotonic_ns))
    out.open()
    out.clock.follow(time.monotonic_ns())

    def read() -> bytes:
        ready, _, _ = select.select([master], [], [], 0.05)
        return os.read(master, 65536) if ready else b""

    answered: list[int] = []
    trips: list[float] = []
    peer = threading.Thread(target=lambda: trips.extend(
        timesync_round_trips(lambda data: os.write(master, data), read, 40, answered)))
    serve_beside(out, peer, lambda: os.close(master), lambda: os.close(slave))
    print(f"round trips: median {np.median(trips):.2f} ms, max {max(trips):.2f} ms over {len(trips)}")
    assert answered == list(range(40))
    # A 5-ms poll would make the median wait 2.5 ms; read on readiness it is the loop's wake-up.
    assert np.median(trips) < 2.0


def test_a_tcp_link_is_watched_on_its_new_descriptor_after_a_reconnection():
    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(10.0)
    url = f"tcp:127.0.0.1:{server.getsockname()[1]}"
    out = MavlinkOutput([endpoint(url)], clock=SensorClock(now=time.monotonic_ns))
    out.open()
    out.clock.follow(time.monotonic_ns())
    ep = out.endpoints[0]
    answered: list[list[int]] = [[], []]
    watched: list[tuple] = []

    def peer() -> None:
        for session in range(2):  # the first connection is dropped by the peer, the link reconnects
            conn, _ = server.accept()
            conn.settimeout(0.05)

            def read() -> bytes:
                try:
                    return conn.recv(65536)
                except socket.timeout:
                    return b""

            timesync_round_trips(conn.sendall, read, 10, answered[session])
            watched.append((ep.watched_fd, ep.transport.fileno()))
            conn.close()

    transport = ep.transport
    serve_beside(out, threading.Thread(target=peer), server.close)
    assert answered == [list(range(10)), list(range(10))]  # every request of both connections answered
    assert transport.counts["link_lost"] >= 1
    assert all(fd is not None and fd == now for fd, now in watched)  # the descriptor the link has, each time


def test_a_flooded_serial_link_rests_then_is_read_to_the_end_losing_nothing():
    # 63 KB of heartbeats: far more than one slice's budget handles, so the link rests, resumes, rests...
    master, slave = pty.openpty()
    out = MavlinkOutput([endpoint(f"{os.ttyname(slave)},921600")])
    out.open()
    enc = mav.MAVLink(None, 1, 1)
    beat = mav.MAVLink_heartbeat_message(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, 0, 0, 0, 3)
    burst = b"".join(beat.pack(enc) for _ in range(3000))
    os.set_blocking(master, False)
    unsent = [memoryview(burst)]

    def write_what_fits() -> None:
        """The burst on into the terminal until its buffer is full (a write would block) or all of it is in."""
        while unsent[0]:
            try:
                unsent[0] = unsent[0][os.write(master, unsent[0][:4096]):]
            except BlockingIOError:
                return

    write_what_fits()  # before the loop looks: its first slice finds more than its budget reads

    def write_all() -> None:
        while unsent[0]:
            select.select([], [master], [], 1.0)
            write_what_fits()
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and out.link_stats()["received"] < 3000:
            time.sleep(0.01)

    serve_beside(out, threading.Thread(target=write_all), lambda: os.close(master), lambda: os.close(slave))
    stats = out.endpoints[0].stats
    print(f"received {out.link_stats()['received']}, dropped over budget {stats['frames_dropped_over_budget']}, "
          f"slices out of budget {stats['read_budget_exhausted']}")
    assert stats["read_budget_exhausted"] >= 2  # it rested, more than once
    # Every frame handled: what a slice read and had no budget for waited for the next one, the rest in the kernel.
    assert out.link_stats()["received"] == 3000 and stats["frames_dropped_over_budget"] == 0
