"""What leaves the service, judged from outside: ``vtolpose run --replay`` with a GPS outage (a stale
sensor) and a long GPS jump (two filter resets, the second one levelling the attitude again), a
pymavlink receiver recording ODOMETRY and a Zenoh subscriber recording ``<prefix>/pose`` and
``<prefix>/status``, all on loopback.

Every published quality is compared with the rule the documentation states (docs/mavlink.md
"Quality", docs/faults.md, docs/running.md "Status"), written out below from those pages rather
than taken from the service: −1 on ODOMETRY (0 on Zenoh) while the pose must not be used; else
100 at σ ≤ 0.1 m and 0.5°, falling on a log scale to 1 at 10 m / 20°; at most 50 while a sensor in
use is stale (no fix used for 1 s); at most 20 for 5 s after a reset. Where the test cannot tell
from outside whether a cap applies (the edges of each window), only the covariance bound is
checked; inside each window the quality must be exactly the rule's value.
"""

import json
import math
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zenoh

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from conftest import free_port
from test_run_daemon import MavlinkListener

REPO_ROOT = Path(__file__).resolve().parents[1]
PREFIX = "vtolpose/vtol1"

# The documented rule (docs/mavlink.md "Quality"; docs/faults.md; config/default.yaml's estimator.health).
POS_SIGMA_GOOD_M, POS_SIGMA_POOR_M = 0.1, 10.0
ATT_SIGMA_GOOD_DEG, ATT_SIGMA_POOR_DEG = 0.5, 20.0
GPS_STALE_AFTER_S = 1.0  # estimator.health.gps_stale_s
STALE_CAP = 50  # estimator.health.stale_quality_cap
RESET_CAP, RESET_HOLD_S = 20, 5.0  # estimator.health.reset_quality_cap, reset_hold_s
GPS_RESET_AFTER_S = 3.0  # estimator.gps_reset_after_s: every fix rejected this long resets
UNUSABLE = {"no_position", "heading_unaligned"}  # docs/outputs.md: pose statuses that forbid use

# The flight: 36 s of landfill, GPS off 5-9 s, GPS 20 m north 12-16 s (times from the first sample).
FLIGHT_S, GPS_OFF, JUMP = 36.0, (5.0, 4.0), (12.0, 4.0)
FAULTS = [f"gps-off:{GPS_OFF[0]:g}:{GPS_OFF[1]:g}", f"gps-jump:{JUMP[0]:g}:20,0,0:{JUMP[1]:g}"]


def documented_quality(var_pos_m2: list[float], var_att_rad2: list[float]) -> int:
    """1-100 from the largest position and attitude standard deviations, on the documented log scale."""
    def score(sigma: float, good: float, poor: float) -> float:
        return min(max(1.0 - math.log10(max(sigma, 1e-12) / good) / math.log10(poor / good), 0.0), 1.0)

    q = min(score(math.sqrt(max(var_pos_m2)), POS_SIGMA_GOOD_M, POS_SIGMA_POOR_M),
            score(math.degrees(math.sqrt(max(var_att_rad2))), ATT_SIGMA_GOOD_DEG, ATT_SIGMA_POOR_DEG))
    return max(1, round(100 * q))


class Windows:
    """Where, in the published poses' time, each cap certainly applies and where none can."""

    def __init__(self, t0_ns: int, gps_t_ns: np.ndarray, delay_s: float, imu_period_ns: int,
                 reset_brackets: list[tuple[int, int]]) -> None:
        s = 1_000_000_000
        off_start, off_end = t0_ns + int(GPS_OFF[0] * s), t0_ns + int(sum(GPS_OFF) * s)
        jump_start = t0_ns + int(JUMP[0] * s)
        last_fix = int(gps_t_ns[gps_t_ns < off_start].max())
        delay_ns = int(delay_s * s)
        # Stale: no fix used for 1 s at the filter's horizon, which the published pose leads by delay_s.
        self.stale = (last_fix + int(GPS_STALE_AFTER_S * s) + delay_ns + imu_period_ns, off_end)
        # A reset is seen between the last ODOMETRY before reset_counter moved and the first after it; its
        # hold covers at least [first after, last before + 5 s).
        self.reset = [(after, before + int(RESET_HOLD_S * s)) for before, after in reset_brackets]
        last_reset_end = reset_brackets[-1][1] + int(RESET_HOLD_S * s) + imu_period_ns
        self.healthy = [(0, off_start + int(GPS_STALE_AFTER_S * s)),
                        (off_end + delay_ns + imu_period_ns, jump_start + int(GPS_STALE_AFTER_S * s)),
                        (last_reset_end, 2**62)]

    def cap(self, t_ns: int) -> int | None:
        """The cap that certainly applies at t_ns (100: certainly none), or None where it is uncertain."""
        caps = [RESET_CAP for a, b in self.reset if a <= t_ns < b]
        if self.stale[0] <= t_ns < self.stale[1]:
            caps.append(STALE_CAP)
        if caps:
            return min(caps)
        return 100 if any(a <= t_ns < b for a, b in self.healthy) else None


def open_subscriber(port: int):
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


@pytest.fixture(scope="module")
def faulty_flight(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("quality") / "landfill"
    write_flight(simulate_flight("landfill", FLIGHT_S, 7), root)
    return root


def test_every_published_quality_follows_the_documented_rule(faulty_flight):
    zenoh_port, mav_port = free_port(), free_port(socket.SOCK_DGRAM)
    listener = MavlinkListener(mav_port)
    listener.conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)  # room for bursts under load
    session = open_subscriber(zenoh_port)
    poses, status = [], []
    session.declare_subscriber(f"{PREFIX}/pose", lambda s: poses.append(json.loads(s.payload.to_string())))
    session.declare_subscriber(f"{PREFIX}/status", lambda s: status.append(json.loads(s.payload.to_string())))
    cmd = [sys.executable, "-m", "vtolpose", "run", "--replay", str(faulty_flight), "--speed", "15", "--hold",
           "--mavlink", f"udpout:127.0.0.1:{mav_port}", "--zenoh",
           "--set", "outputs.zenoh.listen=[]", "--set", f"outputs.zenoh.connect=[tcp/127.0.0.1:{zenoh_port}]",
           *[arg for fault in FAULTS for arg in ("--fault", fault)]]
    proc = subprocess.Popen(cmd, cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        ready = proc.stdout.readline()  # printed once the replay is done; --hold keeps publishing the status
        assert "replay finished" in ready, ready + (proc.stderr.read() if proc.poll() is not None else "")
        n_status = len(status)
        proc.send_signal(signal.SIGTERM)  # one last status on the way out
        out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        listener.close()
        session.close()
    assert len(status) > n_status, "no status after the replay finished"
    odometry = [m for m in listener.messages if m.get_type() == "ODOMETRY"]

    data = Dataset.open(faulty_flight)
    imu_t = data.imu().t_ns
    delay_s = load_config()["fusion.delay_s"]

    # Resets, as the flight controller sees them: where reset_counter moves (by two if a loaded machine lost
    # every ODOMETRY between the resets: each reset then gets the same bracket).
    brackets = [(a.time_usec * 1000, b.time_usec * 1000) for a, b in zip(odometry, odometry[1:])
                for _ in range((b.reset_counter - a.reset_counter) % 256)]
    assert odometry[0].reset_counter == 0 and len(brackets) == 2, brackets
    final = status[-1]
    assert final["filter_resets"] == 2 and final["health"]["resets"] == {"gps_rejected": 2}
    t_reset = final["health"]["last_reset"]["t_ns"]  # the filter's time; the published pose leads by delay_s
    assert brackets[-1][0] < t_reset + delay_s * 1e9 <= brackets[-1][1]
    # docs/faults.md: every fix refused for gps_reset_after_s (from the jump's start) resets the filter.
    first_expected = imu_t[0] + (JUMP[0] + GPS_RESET_AFTER_S + delay_s) * 1e9
    assert brackets[0][0] - 0.05e9 < first_expected <= brackets[0][1] + 0.05e9, (brackets, first_expected)

    windows = Windows(int(imu_t[0]), data.gps().t_ns, delay_s, int(np.median(np.diff(imu_t))), brackets)

    # The status documents: the cap they report follows from what they report degraded, as the rule says.
    # (Their `quality` is the last published pose's, which may predate a reset the health already counts.)
    for doc in status:
        health = doc["health"]
        if "gps_stale" in health["degraded"]:
            assert health["quality_cap"] <= STALE_CAP, doc
        if any(d.startswith("recent_reset") for d in health["degraded"]):
            assert health["quality_cap"] <= RESET_CAP, doc
        if doc["pose_problem"] is not None:
            assert doc["quality"] == 0, doc

    # Zenoh: the poses received (congestion control drop: a loaded machine may lose some).
    assert len(poses) > 0.5 * len(imu_t), len(poses)
    seen = {"stale cap binds": 0, "reset cap binds": 0, "unusable": 0, "healthy": 0}
    by_time = {}
    for pose in poses:
        t, cov = pose["t_ns"], pose["cov"]
        by_time[t] = pose
        finite = cov is not None and all(c is not None for c in cov)
        if pose["status"] in UNUSABLE or not finite:
            assert pose["quality"] == 0, pose
            seen["unusable"] += 1
            continue
        c = np.array(cov, dtype=float).reshape(6, 6).diagonal()
        rule = documented_quality(c[0:3].tolist(), c[3:6].tolist())
        cap = windows.cap(t)
        if cap is None:
            assert 1 <= pose["quality"] <= rule + 1, (t, pose["quality"], rule)
            continue
        assert abs(pose["quality"] - min(rule, cap)) <= 1, (t, pose["quality"], rule, cap)
        if cap == STALE_CAP and rule > STALE_CAP + 1:
            seen["stale cap binds"] += 1
        elif cap == RESET_CAP and rule > RESET_CAP + 1:
            seen["reset cap binds"] += 1
        elif cap == 100:
            seen["healthy"] += 1
    # Every part of the rule was exercised, at IMU rate (125 Hz) for at least a second each.
    assert min(seen.values()) > 125, seen

    # ODOMETRY: the same rule from the message's own covariance; the same quality as the Zenoh pose.
    usable = 0
    for m in odometry:
        t = m.time_usec * 1000
        cov = np.array(m.pose_covariance, dtype=float)  # upper triangle of x, y, z, roll, pitch, yaw
        twin = by_time.get(t)
        if twin is not None and (twin["status"] in UNUSABLE or twin["quality"] == 0):
            assert m.quality == -1, (t, m.quality, twin["status"])
            continue
        if m.quality == -1:
            assert twin is None, (t, twin)  # unusable per the twin never reaches here
            continue
        usable += 1
        assert np.all(np.isfinite(cov)), t
        rule = documented_quality(cov[[0, 6, 11]].tolist(), cov[[15, 18, 20]].tolist())
        cap = windows.cap(t)
        bound = rule if cap is None else min(rule, cap)
        assert 1 <= m.quality <= bound + 2, (t, m.quality, rule, cap)  # roll/pitch/yaw vs the rotation vector
        if cap is not None:
            assert m.quality >= min(rule, cap) - 2, (t, m.quality, rule, cap)
        if twin is not None:
            assert m.quality == twin["quality"], (t, m.quality, twin["quality"])
    assert usable > 0.5 * len(odometry) and len(odometry) > 50 * FLIGHT_S * 0.5, (usable, len(odometry))
