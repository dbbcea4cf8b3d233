"""The MAVLink GPS link under hostile input, with real pymavlink peers on loopback: floods of random
datagrams, of wrongly signed and of unsigned GPS_RAW_INT while the autopilot's signed fixes keep coming
(every fix delivered or its loss counted, nothing forged delivered, nothing grows); a forged message
with a far-future timestamp; thousands of one-shot senders; its settings checked at load."""

import asyncio
import subprocess
import sys
import time
from pathlib import Path

import pytest

from vtolpose.config import ConfigError, load_config
from vtolpose.config.sections import build_sections
from vtolpose.drivers.gps import mavlink_gps as gps_module
from vtolpose.drivers.gps.mavlink_gps import MavlinkGps, MavlinkGpsConfig, mavutil
from vtolpose.drivers.links.mavlink_signing import signing_timestamp
from vtolpose.service.runtime.sources import ThreadedSource

from test_mavlink_gps import free_udp_port

REPO_ROOT = Path(__file__).resolve().parents[1]
mav = mavutil.mavlink
KEY, WRONG_KEY = bytes(range(32)), bytes(range(1, 33))
LAT0 = 58.4  # genuine fixes: LAT0 + k * 1e-6 carries the fix's number k
FORGED_LATS = (10.0, 20.0)  # what the flooders claim: never delivered


def gps_raw(k: int, lat_deg: float = LAT0, step_deg: float = 1e-6) -> object:
    return mav.MAVLink_gps_raw_int_message(1_000_000 + 100_000 * k, 3, round((lat_deg + step_deg * k) * 1e7),
                                           156_000_000, 100_000, 90, 140, 0, 0, 9)


def fix_number(reading) -> int:
    return round((reading.lat_deg - LAT0) / 1e-6)


def signed_peer(port: int, key: bytes = KEY, system: int = 1):
    """The autopilot as pymavlink runs it: a MAVLink 2 link sending signed messages to ``port``."""
    peer = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=system, source_component=1)
    peer.setup_signing(key, sign_outgoing=True)
    return peer


def gps_link(port: int, **kw) -> MavlinkGps:
    gps = MavlinkGps(MavlinkGpsConfig(f"udpin:127.0.0.1:{port}", origin=(LAT0, 15.6, 100.0), system_id=1, **kw))
    gps.open()
    return gps


def read_until(gps: MavlinkGps, done, timeout_s: float = 5.0) -> list:
    readings, deadline = [], time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        readings += gps.read(min(0.05, max(0.0, deadline - time.monotonic())))
        if done(readings):
            break
    return readings


FLOODER = r"""
import os, socket, sys, time
from vtolpose.drivers.gps.mavlink_gps import mavutil
kind, port, seconds, rate = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])
mav = mavutil.mavlink
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
if kind == "random":
    blobs = [os.urandom(n) for n in (8, 64, 280, 1400)] + [b"\xfd" + os.urandom(279), b"\xfe" + os.urandom(200)]
else:  # GPS_RAW_INT as the autopilot's (system 1, component 1), one to a datagram, each a new receiver time
    enc = mav.MAVLink(None, 1, 1)
    if kind == "forged":  # signed with the wrong key, timestamps far in the future
        enc.signing.secret_key, enc.signing.sign_outgoing, enc.signing.timestamp = bytes(range(1, 33)), True, 2**46
    lat = 10.0 if kind == "forged" else 20.0
    blobs = [mav.MAVLink_gps_raw_int_message(5_000_000 + k, 3, round(lat * 1e7), 156000000, 60000, 90, 140, 0, 0, 9)
             .pack(enc) for k in range(2000)]
print("ready", flush=True)
sys.stdin.readline()
start = time.monotonic()
end, sent = start + seconds, 0
while time.monotonic() < end:
    for b in blobs:
        if rate and sent >= rate * (time.monotonic() - start):
            time.sleep(0.001)
            break
        try:
            s.sendto(b, ("127.0.0.1", port))
            sent += 1
        except OSError:  # the socket buffer is full (ENOBUFS): that datagram is not sent, nor counted
            pass
print(sent, flush=True)
"""


def flooders(port: int, seconds: float, rate: float) -> list[subprocess.Popen]:
    procs = []
    for kind in ("random", "forged", "unsigned"):
        proc = subprocess.Popen([sys.executable, "-c", FLOODER, kind, str(port), str(seconds), str(rate)],
                                cwd=REPO_ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert proc.stdout.readline().strip() == "ready"
        procs.append(proc)
    return procs


class CpuMetered:
    """The driver as the reader thread sees it, adding up the CPU time its reads take on that thread."""

    def __init__(self, driver) -> None:
        self.driver, self.cpu_s = driver, 0.0

    def read(self, timeout_s: float):
        start = time.thread_time()
        try:
            return self.driver.read(timeout_s)
        finally:
            self.cpu_s += time.thread_time() - start

    def close(self) -> None:
        self.driver.close()


def run_source(source: ThreadedSource, seconds: float, during) -> list:
    """Consume ``source`` on an event loop for ``seconds`` while ``during()`` runs on a thread."""
    got: list = []

    async def main():
        async def consume():
            async for reading in source:
                got.append(reading)

        task = asyncio.create_task(consume())
        worker = asyncio.get_running_loop().run_in_executor(None, during)
        await asyncio.sleep(seconds)
        await worker
        source.close()
        await asyncio.wait_for(task, 5.0)

    asyncio.run(main())
    return got


@pytest.mark.slow
@pytest.mark.parametrize("rate", [1000.0, 0.0], ids=["within-budget", "flat-out"])
def test_floods_never_deliver_a_forgery_and_every_fix_arrives_or_its_loss_is_counted(rate):
    """Three flooders (random datagrams; GPS_RAW_INT signed with the wrong key and far-future timestamps;
    unsigned GPS_RAW_INT) at ``rate`` datagrams/s each (0: as fast as they can) while the autopilot's
    signed fixes arrive at 20 Hz, read by the runtime's reader thread."""
    port = free_udp_port()
    gps = gps_link(port, signing_key=KEY, require_signing=True)
    metered = CpuMetered(gps)
    source = ThreadedSource("gps", metered, lambda reading: reading)
    procs = flooders(port, 3.0, rate)
    autopilot = signed_peer(port)
    sent: list[int] = []
    held_most, peers = [0], []

    def fly():
        for k in range(80):  # 4 s at 20 Hz; the flood covers the middle 3 s
            autopilot.mav.send(gps_raw(k))
            sent.append(k)
            if k == 10:
                for proc in procs:
                    proc.stdin.write("go\n")
                    proc.stdin.flush()
            held_most[0] = max(held_most[0], len(gps._held))
            time.sleep(0.05)
        peers.extend(gps.peers)

    wall0 = time.monotonic()
    try:
        got = run_source(source, 4.5, fly)
        flood_sent = [int(proc.stdout.readline()) for proc in procs]
    finally:
        autopilot.close()
        for proc in procs:
            proc.kill()
            proc.communicate()
        gps.close()
    reader_share = metered.cpu_s / (time.monotonic() - wall0)
    c = gps.counts
    delivered = [fix_number(r) for r in got]
    lost = len(sent) - len(delivered)
    counted_losses = c["kernel_dropped_datagrams"] + c["frames_dropped_over_budget"]
    print(f"flood {rate or 'flat-out'}/s x3: {sum(flood_sent)} datagrams; fixes {len(delivered)}/{len(sent)}, "
          f"kernel drops {c['kernel_dropped_datagrams']}, frames dropped over budget {c['frames_dropped_over_budget']}, "
          f"budget ran out {c['read_budget_exhausted']} times, refused: unsigned {c['refused_unsigned']}, "
          f"bad signature {c['refused_bad_signature']}; reader thread {reader_share:.1%} of a core")
    assert all(abs(r.lat_deg - lat) > 1.0 for r in got for lat in FORGED_LATS)  # nothing forged, ever
    assert delivered == sorted(set(delivered)) and set(delivered) <= set(sent)  # each genuine fix once, in order
    assert c["received"] == len(delivered)  # every accepted frame was a genuine fix
    assert lost <= counted_losses, "fixes lost without being counted"
    assert min(flood_sent) > 2000 and c["refused_unsigned"] > 100 and c["refused_bad_signature"] > 100
    assert c["bad_bytes"] > 0  # the random datagrams arrived too
    if rate:  # within the budget only a stall of this process on a busy machine could cost a fix
        assert len(delivered) >= 0.95 * len(sent)
    assert held_most[0] <= gps_module.MAX_HELD_FRAMES and len(peers) == 1 and source.dropped == 0
    assert gps.inbound.check.streams == 1  # the forger's far-future stream was never remembered


def test_a_forged_far_future_timestamp_does_not_lock_the_autopilot_out():
    """pymavlink's own check would take the forged timestamp as the stream's newest and refuse every real
    message after it; here the signature is checked first. A replayed message is refused."""
    port = free_udp_port()
    gps = gps_link(port, signing_key=KEY, require_signing=True)
    autopilot = signed_peer(port)
    forger = mav.MAVLink(None, srcSystem=1, srcComponent=1)  # the autopilot's system, component and link id
    forger.signing.secret_key, forger.signing.sign_outgoing = WRONG_KEY, True
    forger.signing.link_id = autopilot.mav.signing.link_id  # the very stream the autopilot signs on
    forger.signing.timestamp = signing_timestamp() + 100_000 * 86400 * 365  # a year ahead
    try:
        autopilot.mav.send(gps_raw(0))
        assert [fix_number(r) for r in read_until(gps, lambda r: r)] == [0]
        autopilot.write(gps_raw(1, lat_deg=10.0, step_deg=0.0).pack(forger))
        recorded = gps_raw(2).pack(autopilot.mav)
        autopilot.write(recorded)
        autopilot.write(recorded)  # played again
        autopilot.mav.send(gps_raw(3))
        readings = read_until(gps, lambda r: len(r) >= 2)
        readings += gps.read(0.2)
    finally:
        autopilot.close()
        gps.close()
    assert [fix_number(r) for r in readings] == [2, 3]
    c = gps.counts
    assert (c["refused_bad_signature"], c["refused_replayed"], c["received"]) == (1, 1, 3)


def test_signing_required_refuses_unsigned_wrongly_signed_and_unknown_ids_and_counts_each(caplog):
    port = free_udp_port()
    gps = gps_link(port, signing_key=KEY, require_signing=True)
    autopilot, imposter = signed_peer(port), signed_peer(port, WRONG_KEY)
    plain = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    try:
        plain.mav.send(gps_raw(0, lat_deg=20.0, step_deg=0.0))
        imposter.mav.send(gps_raw(1, lat_deg=10.0, step_deg=0.0))
        unknown = bytearray(gps_raw(2).pack(autopilot.mav))
        unknown[7:10] = (0xABCDEF).to_bytes(3, "little")  # an id no dialect here knows, signed with the right key
        autopilot.write(bytes(unknown))
        autopilot.mav.heartbeat_send(2, 3, 0, 0, 4)  # the autopilot's other traffic: skipped, not decoded
        autopilot.mav.send(gps_raw(3))
        readings = read_until(gps, lambda r: r)
        readings += gps.read(0.2)
    finally:
        for conn in (autopilot, imposter, plain):
            conn.close()
        gps.close()
    assert [fix_number(r) for r in readings] == [3]
    c = gps.counts
    assert (c["refused_unsigned"], c["refused_bad_signature"], c["refused_unknown_id"]) == (1, 1, 1)
    assert (c["received"], c["other_messages"], c["fixes"]) == (1, 1, 1)
    warned = " / ".join(r.getMessage() for r in caplog.records)
    assert all(f"refused {why}" in warned for why in ("unsigned", "bad signature", "unknown id"))


def test_with_a_key_but_signing_not_required_unsigned_fixes_pass_and_forged_ones_do_not():
    port = free_udp_port()
    gps = gps_link(port, signing_key=KEY)
    plain = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    imposter = signed_peer(port, WRONG_KEY)
    try:
        imposter.mav.send(gps_raw(0, lat_deg=10.0, step_deg=0.0))
        plain.mav.send(gps_raw(1))
        readings = read_until(gps, lambda r: r)
        readings += gps.read(0.2)
    finally:
        plain.close()
        imposter.close()
        gps.close()
    assert [fix_number(r) for r in readings] == [1]
    assert gps.counts["refused_bad_signature"] == 1 and gps.counts["unsigned_accepted"] == 1


def test_a_read_spends_its_cpu_budget_then_rests_and_holds_what_it_read(monkeypatch):
    """With a budget too small for one frame, every slice handles one frame and then the reader rests until
    its share has refilled the budget; frames already read wait (at most MAX_HELD_FRAMES, the rest dropped
    and counted), none is lost."""
    import socket

    monkeypatch.setattr(gps_module, "READ_BUDGET_S", 1e-9)
    monkeypatch.setattr(gps_module, "MAX_CPU_SHARE", 1e-2)  # a rest of about 100 times the work done (a cold
    # first frame can take milliseconds of CPU: 10 000 times that outlasted the wait below)
    monkeypatch.setattr(gps_module, "MAX_HELD_FRAMES", 4)
    port = free_udp_port()
    gps = gps_link(port)
    autopilot = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # six fixes in one datagram
            s.sendto(b"".join(gps_raw(k).pack(autopilot) for k in range(6)), ("127.0.0.1", port))
        first = gps.read(0.5)
        resting = gps.read(0)  # within the rest: nothing is handled
        later = read_until(gps, lambda r: len(r) >= 3, 20.0)
    finally:
        gps.close()
    assert [fix_number(r) for r in first] == [0] and resting == []
    assert [fix_number(r) for r in later] == [1, 2, 3]
    assert gps.counts["frames_dropped_over_budget"] == 2 and gps.counts["read_budget_exhausted"] == 4


def test_datagrams_the_kernel_drops_are_counted():
    """A flood beyond what is read fills the socket; the kernel's own drop count says how much was lost."""
    import socket

    from vtolpose.drivers.links.mavlink_transport import UdpTransport

    port = free_udp_port()
    udp = UdpTransport(f"udpin:127.0.0.1:{port}")
    udp.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # room for a few datagrams only
    heartbeat = mav.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(mav.MAVLink(None, 1, 1))
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for _ in range(500):
                s.sendto(heartbeat, ("127.0.0.1", port))
            received = 0
            for _ in range(2):  # the count rides on the next datagram that got in
                while True:
                    frames, more = udp.receive(64)
                    received += len(frames)
                    if not more:
                        break
                s.sendto(heartbeat, ("127.0.0.1", port))
    finally:
        udp.close()
    assert received < 100 and received + udp.counts["kernel_dropped_datagrams"] == 501


def test_thousands_of_one_shot_senders_leave_the_peer_list_bounded():
    """pymavlink's udpin kept every sender's address for good; this link remembers at most MAX_PEERS."""
    import socket

    port = free_udp_port()
    gps = gps_link(port)
    autopilot = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    try:
        autopilot.mav.send(gps_raw(0))
        assert read_until(gps, lambda r: r)
        first = gps.peers[0]
        stranger = mav.MAVLink(None, srcSystem=1, srcComponent=1)
        for k in range(1, 3001):  # valid fixes of the vehicle's system, each from a port of its own, once
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                s.sendto(gps_raw(k).pack(stranger), ("127.0.0.1", port))
            if k % 10 == 0:  # 2000 fixes a second: within the reader's share of a core
                read_until(gps, lambda r: False, 0.005)
            if k % 100 == 0:  # the autopilot keeps talking: it keeps its place
                autopilot.mav.send(gps_raw(10_000 + k))
        read_until(gps, lambda r: False, 0.3)
        peers = gps.peers
    finally:
        autopilot.close()
        gps.close()
    assert gps.counts["fixes"] > 2900  # they did arrive, and were used (no signing here)
    assert len(peers) == gps_module.MAX_PEERS and first in peers and gps.counts["peers_refused_full"] > 2800


def test_the_runtime_reader_queue_is_bounded_and_counts_what_it_drops():
    """ThreadedSource keeps at most ``max_queue`` fixes while the loop does not take them; the oldest go first."""
    port = free_udp_port()
    gps = gps_link(port)
    source = ThreadedSource("gps", gps, lambda reading: reading, max_queue=50)
    autopilot = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)

    async def main():
        samples = source.__aiter__()
        autopilot.mav.send(gps_raw(0))
        first = await asyncio.wait_for(samples.__anext__(), 5.0)  # the reader thread runs from here on
        for k in range(1, 301):  # nobody takes these for now
            autopilot.mav.send(gps_raw(k))
            if k % 25 == 0:  # paced within the reader's share of a core: none is lost before the queue
                await asyncio.sleep(0.02)
        deadline = time.monotonic() + 5.0
        while source.dropped < 250 and time.monotonic() < deadline:  # all read and queued (or dropped)
            await asyncio.sleep(0.02)
        await asyncio.sleep(0.1)  # nothing more comes
        rest = []
        while True:
            try:
                rest.append(await asyncio.wait_for(samples.__anext__(), 0.3))
            except asyncio.TimeoutError:
                break
        await samples.aclose()
        return [fix_number(r) for r in [first, *rest]]

    try:
        got = asyncio.run(main())
    finally:
        autopilot.close()
        gps.close()
    assert gps.counts["fixes"] == 301 and source.dropped == 250 and got == [0, *range(251, 301)]


def free_tcp_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_tcp_link_that_is_not_there_yet_is_waited_for_and_read():
    port = free_tcp_port()
    gps = MavlinkGps(MavlinkGpsConfig(f"tcp:127.0.0.1:{port}", origin=(LAT0, 15.6, 100.0), system_id=1))
    gps.open()
    try:
        assert gps.read(0.3) == [] and gps.status.startswith("waiting for")
        autopilot = mavutil.mavlink_connection(f"tcpin:127.0.0.1:{port}", source_system=1, source_component=1)
        try:
            readings, deadline, k = [], time.monotonic() + 10.0, 0
            while not readings and time.monotonic() < deadline:
                autopilot.recv()  # accepts the connection once it comes
                autopilot.mav.send(gps_raw(k))
                k += 1
                readings += gps.read(0.1)
        finally:
            autopilot.close()
    finally:
        gps.close()
    assert readings and gps.counts["open_failures"] >= 1 and gps.status == "closed"


# ------------------------------------------------------------------------------ configuration


def gps_config(cfg: dict) -> MavlinkGpsConfig:
    sections = build_sections(cfg)
    return MavlinkGpsConfig.from_section(sections.sensors.gps, sections.vehicle.system_id)


def write_key(tmp_path, name="gps.key", mode=0o600):
    path = tmp_path / name
    path.write_bytes(KEY)
    path.chmod(mode)
    return str(path)


def test_the_default_listens_on_loopback_and_takes_only_the_vehicle_system():
    cfg = load_config(None, {"sensors": {"gps": {"type": "mavlink"}}})
    conf = gps_config(cfg)
    assert conf.url.startswith("udpin:127.0.0.1:") and conf.system_id == cfg["vehicle.system_id"] == 1
    assert conf.signing_key is None and conf.require_signing is False


def test_signing_settings_are_read_and_a_bad_key_names_the_key(tmp_path):
    key = write_key(tmp_path)
    cfg = load_config(None, {"sensors": {"gps": {"type": "mavlink", "signing_key_file": key, "require_signing": True}}})
    conf = gps_config(cfg)
    assert conf.signing_key == KEY and conf.require_signing
    Path(key).write_bytes(b"x" * 31)  # changed after the check at load: caught when read
    with pytest.raises(ConfigError, match=r"key 'sensors.gps.signing_key_file': .*32 raw bytes"):
        gps_config(cfg)


@pytest.mark.parametrize("gps, outputs, key, message", [
    ({"require_signing": True}, {}, "sensors.gps.require_signing", "needs sensors.gps.signing_key_file"),
    ({"signing_key_file": "WORLD"}, {}, "sensors.gps.signing_key_file", r"readable or writable by every user"),
    ({"signing_key_file": "MISSING"}, {}, "sensors.gps.signing_key_file", "No such file"),
    ({"mavlink_url": "udpout:127.0.0.1:14550"}, {}, "sensors.gps.mavlink_url", "udpout binds no port"),
    ({"mavlink_url": "tcpin:127.0.0.1:14550"}, {}, "sensors.gps.mavlink_url", "tcpin is not served"),
    ({"mavlink_url": "udpin:127.0.0.1"}, {}, "sensors.gps.mavlink_url", "expected HOST:PORT"),
    # The GPS on the flight controller's link: that link's signing applies and may not be weakened.
    ({"mavlink_url": "udpout:127.0.0.1:14540", "signing_key_file": "GOOD"}, {"enabled": True},
     "sensors.gps.signing_key_file", "set outputs.mavlink.signing_key_file"),
    ({"mavlink_url": "udpout:127.0.0.1:14540", "signing_key_file": "GOOD", "require_signing": True},
     {"enabled": True, "signing_key_file": "GOOD"}, "sensors.gps.require_signing",
     "set outputs.mavlink.require_signing: true"),
])
def test_bad_gps_link_settings_are_refused_naming_the_key(tmp_path, gps, outputs, key, message):
    files = {"GOOD": write_key(tmp_path), "WORLD": write_key(tmp_path, "world.key", 0o644),
             "MISSING": str(tmp_path / "missing.key")}
    named = lambda d: {k: files.get(v, v) if isinstance(v, str) else v for k, v in d.items()}  # noqa: E731
    with pytest.raises(ConfigError, match=rf"key '{key}': .*{message}"):
        load_config(None, {"sensors": {"gps": {"type": "mavlink", **named(gps)}}, "outputs": {"mavlink": named(outputs)}})


def test_the_gps_may_repeat_the_shared_links_signing_settings(tmp_path):
    key = write_key(tmp_path)
    link = {"enabled": True, "signing_key_file": key, "require_signing": True}
    cfg = load_config(None, {"sensors": {"gps": {"type": "mavlink", "mavlink_url": "udpout:127.0.0.1:14540",
                                                 "signing_key_file": key, "require_signing": True}},
                             "outputs": {"mavlink": link}})
    assert cfg["sensors.gps.require_signing"] and cfg["outputs.mavlink.require_signing"]


def test_with_signing_required_nothing_unsigned_or_forged_is_decoded(monkeypatch):
    """The signature is checked on the frame's bytes first: the decoder never sees a refused frame."""
    port = free_udp_port()
    gps = gps_link(port, signing_key=KEY, require_signing=True)
    decoded = []
    decode = gps.inbound._decoder.decode
    monkeypatch.setattr(gps.inbound._decoder, "decode", lambda buf: decoded.append(bytes(buf)) or decode(buf))
    autopilot, imposter = signed_peer(port), signed_peer(port, WRONG_KEY)
    plain = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    try:
        for k in range(3):
            imposter.mav.send(gps_raw(k, lat_deg=10.0, step_deg=0.0))
            plain.mav.send(gps_raw(k, lat_deg=20.0, step_deg=0.0))
        time.sleep(0.1)
        autopilot.mav.send(gps_raw(5))
        readings = read_until(gps, lambda r: r)
    finally:
        for conn in (autopilot, imposter, plain):
            conn.close()
        gps.close()
    assert [fix_number(r) for r in readings] == [5]
    assert (gps.counts["refused_bad_signature"], gps.counts["refused_unsigned"]) == (3, 3)
    assert len(decoded) == 1 and decoded[0][-13] == autopilot.mav.signing.link_id  # the autopilot's frame only


def test_the_gps_links_counters_are_in_the_status_document():
    from vtolpose.config import load_config
    from vtolpose.drivers.simulator import simulate_flight
    from vtolpose.service.runtime.daemon import build_runtime, serve

    port = free_udp_port()
    gps = gps_link(port, signing_key=KEY, require_signing=True)
    source = ThreadedSource("gps", gps, lambda reading: reading.fix)
    runtime = build_runtime(load_config(), simulate_flight("landfill", 2.0, 1).calibration)
    autopilot, imposter = signed_peer(port), signed_peer(port, WRONG_KEY)
    plain = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)

    async def feed():
        await asyncio.sleep(0.2)
        for k in range(3):
            autopilot.mav.send(gps_raw(k))
        imposter.mav.send(gps_raw(7, lat_deg=10.0, step_deg=0.0))
        for k in range(2):
            plain.mav.send(gps_raw(8 + k, lat_deg=20.0, step_deg=0.0))
        await asyncio.sleep(0.5)

    async def main():
        task = asyncio.create_task(serve(runtime, [source], duration_s=1.0, handle_signals=False))
        await feed()
        return await task

    try:
        summary = asyncio.run(main())
    finally:
        for conn in (autopilot, imposter, plain):
            conn.close()
        gps.close()
    link = summary.status["inputs"]["gps"]
    assert (link["received"], link["refused"], link["unsigned"]) == (3, 3, 2), link
    assert link["signing"] == "required" and link["counters"]["refused_bad_signature"] == 1
    assert link["url"] == f"udpin:127.0.0.1:{port}"
