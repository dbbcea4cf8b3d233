"""Runtime benchmarks: pose latency under camera load, and memory over a one-hour replay.

``runtime-latency``: simulated IMU and GPS arrive in real time through the live path (a reader
thread per device handing samples to the loop), a camera thread delivers 656 × 494 frames at
7.5 Hz whose SIFT extraction runs in the runtime's camera workers (threads, then processes:
``fusion.camera_process``, the two compared in the same run), ODOMETRY goes out over UDP at
every sample and every pose is published on Zenoh to a subscriber in another process. The
latency is from the moment a sample is handed over by its reader thread to the moment both
outputs have returned. Targets: p99 ≤ 1 ms, and the loop's own handling of a sample ≤ 0.2 ms (p50).
Beside them: each output's share of the handling, and what a bare UDP datagram and a bare Zenoh put
of the same sizes cost on this machine with nothing around them (the floor of the two sends), and what the code
that runs after an idle gap as long as an IMU period pays for the gap (the idle floor: the same encoding warm in a
loop, after a sleep, after a spin). Those runs'
frames are one textured image, not of the flight, so their update only counts. Two last runs render the flight
and fuse its own frames with the service's frame processor: the EKF-SLAM update on the fusion thread
(``fusion.update_thread``, the default; ``service/runtime/fusion_thread.py``), then on the loop (the baseline),
where the IMU samples that arrive during an update wait for it.

``runtime-hour``: a one-hour landfill flight replayed through the runtime as fast as possible
with both outputs enabled; resident memory, history and buffers are sampled along the way and
must stay flat.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.drivers.simulator.render import default_camera
from vtolpose.estimator import CameraFrame, GpsFix, ImuSample
from vtolpose.service.replay.session import FrameProcessor
from vtolpose.service.runtime.daemon import build_runtime, serve
from vtolpose.service.commands.run import camera_processor
from vtolpose.service.runtime.loop import set_thread_priority
from vtolpose.service.runtime.sources import ReplayClock, ReplaySource, ThreadedSource
from vtolpose.service.runtime.wiring import camera_options, feature_options
from vtolpose.service.runtime.status import LatencyProbe, resident_memory_mb
from vtolpose.service.bench.rows import Row


_SUBSCRIBER = """
import sys, time, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("connect/endpoints", '["tcp/127.0.0.1:%d"]')
conf.insert_json5("scouting/multicast/enabled", "false")
s = zenoh.open(conf)
n = [0]
sub = s.declare_subscriber("%s/pose", lambda sample: n.__setitem__(0, n[0] + 1))
print("ready", flush=True)
sys.stdin.read()
print(n[0], flush=True)
"""


_UDP_SINK = """
import socket, sys, threading
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind(("127.0.0.1", %d))
n = [0]
def count():
    while True:
        s.recv(4096)
        n[0] += 1
threading.Thread(target=count, daemon=True).start()
print("ready", flush=True)
sys.stdin.read()
print(n[0], flush=True)
"""


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _Paced:
    """A fake device: hands out its samples when they are due on the host clock (like a serial driver)."""

    def __init__(self, samples: list[Any], t0_wall: float, t0_data: int) -> None:
        self.samples = samples
        self.t0_wall, self.t0_data = t0_wall, t0_data
        self.k = 0
        self.ended = False

    def _due(self, sample: Any) -> float:
        return self.t0_wall + (sample.t_ns - self.t0_data) * 1e-9

    def read(self, timeout_s: float) -> list[Any]:
        if self.k >= len(self.samples):
            self.ended = True
            return []
        wait = self._due(self.samples[self.k]) - time.perf_counter()
        if wait > timeout_s:
            time.sleep(timeout_s)
            return []
        if wait > 0:
            time.sleep(wait)
        out = []
        now = time.perf_counter()
        while self.k < len(self.samples) and self._due(self.samples[self.k]) <= now:
            out.append(self.samples[self.k])
            self.k += 1
        return out

    def close(self) -> None:
        """A list of samples holds no device."""


def _test_image(seed: int = 0) -> np.ndarray:
    """A 656 × 494 textured grey image: SIFT finds about 800 features in it, like an aerial frame."""
    import cv2  # on first use: a process that never needs OpenCV never loads it (~16 MB)

    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur((rng.random((494, 656)) * 255).astype(np.uint8), (0, 0), 2.0)


def bench_runtime_latency(duration_s: float = 15.0) -> list[Row]:
    """IMU sample in → ODOMETRY and Zenoh pose out, p50/p99, with SIFT at 7.5 Hz in camera threads, then processes (targets: p99 ≤ 1 ms, handling p50 ≤ 0.2 ms)."""
    in_process = {"fusion": {"camera_process": True}}
    rows = idle_floor_rows() + latency_run(duration_s, None, "normal")
    processes = latency_run(duration_s, None, "camera process", in_process)
    rows += processes + process_ratios(rows, processes)
    # The flight's own frames fused: the update on the fusion thread (the default), then on the loop (the baseline).
    fused = latency_run(duration_s, None, "frames fused, update thread", in_process, frames_of_flight=True)
    on_loop = latency_run(duration_s, None, "frames fused, update on the loop",
                          {"fusion": {"camera_process": True, "update_thread": False}}, frames_of_flight=True)
    rows += fused + on_loop + [
        (f"frames fused: update thread / update on the loop: {what}", figure(fused, what) / figure(on_loop, what), "x",
         "the same bench, the same run; below 1: the thread is better")
        for what in ("MAVLink+Zenoh out, p50", "MAVLink+Zenoh out, p99", "MAVLink+Zenoh out, max")]
    if set_thread_priority(20) and set_thread_priority(None):  # permitted here: measure it too
        threads = latency_run(duration_s, 20, "SCHED_FIFO 20")
        processes = latency_run(duration_s, 20, "SCHED_FIFO 20, camera process", in_process)
        rows += threads + processes + process_ratios(threads, processes, "SCHED_FIFO 20: ")
    else:
        rows.append(("(real-time priority not permitted here: not measured)", 0.0, "", "needs CAP_SYS_NICE"))
    return rows


def figure(rows: list[Row], what: str) -> float:
    """The value of the row whose name ends with ``what``."""
    return next(row[1] for row in rows if row[0].endswith(what))


def process_ratios(threads: list[Row], processes: list[Row], label: str = "") -> list[Row]:
    """Camera processes against camera threads, figure by figure, from the two runs just made."""
    return [(f"{label}camera process / camera threads: {what}", figure(processes, what) / figure(threads, what), "x",
             "the same bench, the same run; below 1: the process is better")
            for what in ("MAVLink+Zenoh out, p50", "MAVLink+Zenoh out, p99", "handling on the loop, p50",
                         "handling on the loop, p99")]


class _CountingProcessor(FrameProcessor):
    """The service's frame processor whose update only counts: the bench's frames are not of the flight."""

    def __init__(self, options: Any, shape: tuple[int, int]) -> None:
        super().__init__(options, shape)
        self.features: list[int] = []

    def fusing(self, frame: CameraFrame, features: Any) -> Any:
        self.extract_ms.append(features.extract_ms)
        self.features.append(len(features))
        return lambda est: None  # the measurement hook, as process_features will use it


def latency_run(duration_s: float, priority: int | None, label: str, overrides: dict | None = None,
                frames_of_flight: bool = False, after_warm_up: Callable[[Any], None] | None = None) -> list[Row]:
    """One configuration's latency. ``frames_of_flight``: the flight is rendered and its own frames are fused
    by the service's frame processor (the EKF-SLAM update on the loop, as in service), instead of one textured
    image whose update only counts. ``after_warm_up``: called with the runtime once the filter runs, before the
    measured part (``latency_floor`` stands in for parts of the per-sample work there)."""
    zenoh_port, mav_port = free_port(), free_port(socket.SOCK_DGRAM)
    flight_frames: list[tuple[int, np.ndarray]] = []
    with tempfile.TemporaryDirectory() as tmp:
        write_flight(simulate_flight("landfill", duration_s + 15.0, 1), Path(tmp) / "d",
                     camera=default_camera() if frames_of_flight else None)
        dataset = Dataset.open(Path(tmp) / "d")
        imu, gps = dataset.imu(), dataset.gps()
        t_split = int(imu.t_ns[0]) + 15_000_000_000
        if frames_of_flight:  # in memory before the clock starts: the bench measures the loop, not the disk
            flight_frames = [(t, dataset.load_frame(path)) for t, path in dataset.camera_frames() if t >= t_split]
    cfg = load_config(None, {
        "vehicle": {"name": "bench"},
        "outputs": {
            "mavlink": {"enabled": True, "url": f"udpout:127.0.0.1:{mav_port}", "rate_hz": 1000.0},
            "zenoh": {"enabled": True, "listen": [f"tcp/127.0.0.1:{zenoh_port}"], "multicast_scouting": False},
        },
        **(overrides or {}),
    })
    # Start the filter on the first 15 s of data (alignment), then measure over the rest in real time.
    imu_samples = [ImuSample(int(t), g, a) for t, g, a in zip(imu.t_ns, imu.gyro, imu.accel)]
    gps_fixes = [GpsFix(int(t), p, float(h), float(v)) for t, p, h, v in zip(gps.t_ns, gps.p_ned, gps.sigma_h, gps.sigma_v)]
    image = _test_image()
    options = feature_options(cfg)  # the service's own extraction, as features.* configure it
    if frames_of_flight:
        extract = camera_processor(cfg, dataset.calibration)  # the service's own: it fuses what it extracts
        extract_ms, reports = extract.extract_ms, extract.reports
        features = [report.n_features for report in reports]  # filled in as frames are fused (read after the run)
    else:
        extract = _CountingProcessor(options, image.shape)
        features, extract_ms, reports = extract.features, extract.extract_ms, None

    runtime = build_runtime(cfg, dataset.calibration, camera_processor=extract, measure_latency=True)
    runtime.options.realtime_priority = priority
    for s in sorted(imu_samples[: np.searchsorted(imu.t_ns, t_split)] + [f for f in gps_fixes if f.t_ns < t_split],
                    key=lambda s: (s.t_ns, isinstance(s, GpsFix))):
        runtime.handle(s)
    runtime.latency, runtime.handling = LatencyProbe(), LatencyProbe()  # forget the warm-up
    if after_warm_up is not None:
        after_warm_up(runtime)
    # The peers run in their own processes, as the flight controller and the mapper would.
    subscriber = subprocess.Popen([sys.executable, "-c", _SUBSCRIBER % (zenoh_port, "vtolpose/bench")],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    autopilot = subprocess.Popen([sys.executable, "-c", _UDP_SINK % mav_port], stdin=subprocess.PIPE,
                                 stdout=subprocess.PIPE, text=True)

    async def main() -> Any:
        t0_wall = time.perf_counter() + 1.0
        later_imu = [s for s in imu_samples if s.t_ns >= t_split]
        later_gps = [f for f in gps_fixes if f.t_ns >= t_split]
        frames = ([CameraFrame(t, frame, k) for k, (t, frame) in enumerate(flight_frames)] if frames_of_flight else
                  [CameraFrame(t, image, k) for k, t in enumerate(range(t_split, int(imu.t_ns[-1]), int(1e9 / 7.5)))])
        sources = [
            ThreadedSource("imu", _Paced(later_imu, t0_wall, t_split), lambda s: s, read_timeout_s=0.05),
            ThreadedSource("gps", _Paced(later_gps, t0_wall, t_split), lambda s: s, read_timeout_s=0.05),
            ThreadedSource("camera", _Paced(frames, t0_wall, t_split), lambda s: s, read_timeout_s=0.05),
        ]
        return await serve(runtime, sources, duration_s=duration_s + 5.0, handle_signals=False)

    try:
        subscriber.stdout.readline()
        autopilot.stdout.readline()
        summary = asyncio.run(main())
        subscriber.stdin.close()
        autopilot.stdin.close()
        received = int(subscriber.stdout.readline() or 0)
        datagrams = int(autopilot.stdout.readline() or 0)
    finally:
        for peer in (subscriber, autopilot):
            peer.kill()
            peer.wait()
    p50, p99, pmax = runtime.latency.percentiles_ms(50, 99, 100)
    h50, h99 = runtime.handling.percentiles_ms(50, 99)
    shares = [(f"[{label}]   of which {name} publish, p50", probe.percentiles_ms(50)[0] * 1e3, "us", "its publish call")
              for name, probe in runtime.publishing.items()]
    datagram, document = _bare_send_sizes(runtime)
    udp_us, put_us, udp_got, put_got = bare_sends_us(datagram, document)
    n = len(runtime.latency)
    load = f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores"
    if reports is not None:
        features = [report.n_features for report in reports]
    extract_note = (f"{np.mean(extract_ms):.0f} ms each, {np.mean(features):.0f} features kept; "
                    f"{summary.status['events'].get('camera_frames_dropped_busy', 0)} dropped busy") if features else "no frames"
    return [
        (f"[{label}] IMU in -> MAVLink+Zenoh out, p50", p50 * 1e3, "us", f"{n} samples, {load}"),
        Row(f"[{label}] IMU in -> MAVLink+Zenoh out, p99", p99 * 1e3, "us", "", "<= 1000"),
        (f"[{label}] IMU in -> MAVLink+Zenoh out, max", pmax * 1e3, "us", ""),
        Row(f"[{label}]   of which handling on the loop, p50", h50 * 1e3, "us", "the rest: waiting to be scheduled", "<= 200"),
        (f"[{label}]   of which handling on the loop, p99", h99 * 1e3, "us", ""),
        *shares,
        (f"[{label}] floor: a bare UDP datagram + a bare Zenoh put, p50", udp_us + put_us, "us",
         f"{udp_us:.0f} + {put_us:.0f} us for {datagram} + {document} bytes to peers in other processes, "
         f"paced at 1 kHz, nothing else in the loop; {udp_got} and {put_got} of 2000 received"),
        (f"[{label}] camera frames through {options.detector.upper()} in the "
         f"{'camera process' if runtime.options.camera_process else 'camera threads'}", float(len(features)), "frames",
         extract_note),
        *([] if reports is None else [_update_row(label, list(reports), runtime.options.update_thread)]),
        (f"[{label}] Zenoh poses received by the subscriber process", float(received), "poses",
         f"{summary.status['outputs'].get('mavlink', {}).get('odometry_sent', 0)} ODOMETRY sent, "
         f"{datagrams} datagrams received by the UDP peer"),
    ]


def _update_row(label: str, reports: list, on_thread: bool) -> Row:
    """The frames' EKF-SLAM updates: how many were fused and how long each took (CPU), on the thread or the loop."""
    timed = [r.timing_ms["cpu"] for r in reports if r.timing_ms]
    used = sum(1 for r in reports if r.accepted)
    if not timed:
        return Row(f"[{label}] camera updates", 0.0, "frames", f"{len(reports)} frames reached the filter, none updated")
    where = ("on the fusion thread: the poses go on meanwhile" if on_thread else
             "on the loop: IMU samples arriving meanwhile wait")
    return Row(f"[{label}] camera updates, p50", float(np.median(timed)) * 1e3, "us",
               f"{len(timed)} frames updated ({used} accepted, map up to {max(r.n_landmarks for r in reports)} landmarks), "
               f"p95 {np.percentile(timed, 95):.1f} ms, max {max(timed):.1f} ms, {where}")


def _bare_send_sizes(runtime: Any) -> tuple[int, int]:
    """Bytes of the largest ODOMETRY frame (MAVLink v2, unsigned: a 10-byte header, the 233-byte payload and
    the checksum) and of the last pose document sent."""
    from vtolpose.service.outputs.pose_json import PoseJson

    pose = runtime.last_pose
    return 245, len(PoseJson()(pose, 0, None)) if pose is not None else 900


def bare_sends_us(datagram: int, document: int, count: int = 2000) -> tuple[float, float, int, int]:
    """p50 [us] of a UDP ``sendto`` of ``datagram`` bytes and of a Zenoh ``put`` of ``document`` bytes (as the
    pose publisher is declared: express, real-time priority, drop on congestion), each to a peer in another
    process, paced at 1 kHz: the system's part of the two sends, with no estimator around them. Then how
    many datagrams and puts the peers received (a put nobody subscribes to would cost less)."""
    import zenoh

    zenoh_port, udp_port = free_port(), free_port(socket.SOCK_DGRAM)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{zenoh_port}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    subscriber, sink = peers = [
        subprocess.Popen([sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        for script in (_SUBSCRIBER % (zenoh_port, "vtolpose/floor"), _UDP_SINK % udp_port)]
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        publisher = session.declare_publisher("vtolpose/floor/pose", congestion_control=zenoh.CongestionControl.DROP,
                                              express=True, priority=zenoh.Priority.REAL_TIME)
        for peer in peers:
            peer.stdout.readline()
        time.sleep(0.5)  # the subscriber's interest reaches this session
        frame, payload = bytes(datagram), b"x" * document
        address = ("127.0.0.1", udp_port)
        udp, put = np.zeros(count), np.zeros(count)
        for k in range(count):
            t0 = time.perf_counter_ns()
            sock.sendto(frame, address)
            t1 = time.perf_counter_ns()
            publisher.put(payload)
            udp[k], put[k] = t1 - t0, time.perf_counter_ns() - t1
            time.sleep(0.001)
        time.sleep(0.2)  # the last ones arrive
        publisher.undeclare()
        received = []
        for peer in (sink, subscriber):
            peer.stdin.close()
            received.append(int(peer.stdout.readline() or 0))
    finally:
        sock.close()
        for peer in peers:
            peer.kill()
            peer.wait()
        session.close()
    return float(np.median(udp)) * 1e-3, float(np.median(put)) * 1e-3, received[0], received[1]


def after_idle_us(work: Callable[[], Any], gap_s: float, count: int = 500) -> tuple[float, float, float]:
    """p50 [us] of ``work()`` run ``count`` times back to back (warm), after sleeping ``gap_s`` before each call
    (as the loop sleeps between IMU samples) and after spinning ``gap_s`` before each (the core kept busy). The
    gaps themselves are not timed, only the calls."""
    def timed(wait: Callable[[], None] | None) -> float:
        work()
        spent = np.zeros(count)
        for k in range(count):
            if wait is not None:
                wait()
            t0 = time.perf_counter_ns()
            work()
            spent[k] = time.perf_counter_ns() - t0
        return float(np.median(spent)) * 1e-3

    def spin() -> None:
        end = time.perf_counter() + gap_s
        while time.perf_counter() < end:
            pass  # busy on purpose: the core stays with this process instead of going idle

    return timed(None), timed(lambda: time.sleep(gap_s)), timed(spin)


def idle_floor_rows(gap_s: float = 0.008, count: int = 500) -> list[Row]:
    """What an idle gap as long as an IMU period costs the code that runs after it, on this machine: the ODOMETRY
    encoding of a pose (fields and payload, pure Python, no send) warm in a loop, after a sleep, after a spin."""
    from vtolpose.service.bench.odometry_encoding import bench_poses
    from vtolpose.service.outputs.mavlink_odometry import PROFILES, odometry_fields, odometry_payload

    poses, profile, i = bench_poses(), PROFILES["px4"], [0]

    def encode() -> None:
        i[0] = (i[0] + 1) % len(poses)
        odometry_payload(odometry_fields(poses[i[0]], profile))

    warm, slept, spun = after_idle_us(encode, gap_s, count)
    gap = f"{gap_s * 1e3:.0f} ms"
    return [
        ("idle floor: ODOMETRY encoding, warm in a loop, p50", warm, "us", "the same work as below, back to back"),
        (f"idle floor: the same after sleeping {gap}, p50", slept, "us",
         f"{slept / warm:.2f}x the warm figure: what the loop meets after waiting for a sample"),
        (f"idle floor: the same after spinning {gap}, p50", spun, "us",
         f"{spun / warm:.2f}x the warm figure: the core kept busy instead of idle"),
    ]


class _LogCounter(logging.Handler):
    """Counts the warnings and errors logged during a soak (the first few kept to show)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.counts = {"WARNING": 0, "ERROR": 0, "CRITICAL": 0}
        self.first: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.counts[record.levelname] = self.counts.get(record.levelname, 0) + 1
        if len(self.first) < 3:
            self.first.append(f"{record.levelname} {record.name}: {record.getMessage()[:120]}")


def bench_runtime_hour(duration_s: float = 3600.0, every_s: float = 300.0, camera: bool = False) -> list[Row]:
    """One hour of IMU+GPS (landfill) through the runtime at full speed: memory and buffers stay flat."""
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "hour"
        write_flight(simulate_flight("landfill", duration_s, 1), root, camera=default_camera() if camera else None)
        dataset = Dataset.open(root)
        cfg = load_config(None, {"vehicle": {"name": "bench"}, "features": {"detector": "orb"}, "outputs": {
            "mavlink": {"enabled": True, "url": f"udpout:127.0.0.1:{free_port(socket.SOCK_DGRAM)}"},
            "zenoh": {"enabled": True, "listen": [f"tcp/127.0.0.1:{free_port()}"], "multicast_scouting": False},
        }})
        sensors = ["imu", "camera", "gps"] if camera else ["imu", "gps"]
        frames, load = (dataset.camera_frames(), dataset.load_frame) if camera else (None, None)
        source = ReplaySource(dataset, sensors, ReplayClock(0.0), None, frames, load)
        processor = camera_processor(cfg, dataset.calibration) if camera else None
        runtime = build_runtime(cfg, dataset.calibration, lockstep=True, trajectory_path=Path(tmp) / "traj.txt",
                                camera_processor=processor)
        samples: list[tuple[float, float, int, int, int, int]] = []
        t_first = int(source.imu.t_ns[0])

        def sample(t_ns: int) -> None:
            samples.append(((t_ns - t_first) * 1e-9, resident_memory_mb() or float("nan"), len(runtime.history),
                            runtime.history.capacity, runtime.fusion.buffered_imu, runtime.est.status().landmarks))

        async def sampled() -> Any:
            next_t = t_first + int(60e9)  # from the first minute on: the filter is running by then
            async for item in source:
                t_ns = item.t_ns if isinstance(item.t_ns, int) else int(item.t_ns[-1])  # a sample or an IMU batch
                if t_ns >= next_t:
                    sample(t_ns)
                    next_t += int(every_s * 1e9)
                yield item
            sample(t_ns)

        logs = _LogCounter()
        logging.getLogger().addHandler(logs)
        try:
            summary = asyncio.run(serve(runtime, [sampled()], handle_signals=False))
        finally:
            logging.getLogger().removeHandler(logs)
    first, last = samples[0], samples[-1]
    what = "IMU+camera+GPS (ORB)" if camera else "IMU+GPS"
    failures = sum(f["failures"] for f in runtime.failures.report().values())
    status = runtime.est.status()
    rows: list[Row] = [
        (f"{duration_s / 60:.0f}-minute {what} replay speed", summary.data_s / summary.wall_s, "x real time",
         f"{summary.wall_s:.1f} s wall, both outputs on"),
        (f"resident memory at {first[0] / 60:.0f} min", first[1], "MB", "the filter running, history filling"),
        (f"resident memory at {last[0] / 60:.0f} min", last[1], "MB", f"max {max(s[1] for s in samples):.1f} MB"),
        ("pose history entries at the end", float(last[2]), "poses",
         f"capacity {last[3]}, span {runtime.options.history_s:g} s"),
        ("IMU samples buffered ahead of the horizon", float(last[4]), "samples", f"delay {runtime.fusion.delay_ns * 1e-9:g} s"),
        ("isolated failures (outputs, sources, handling)", float(failures), "", ", ".join(runtime.failures.report()) or "none"),
        ("errors logged", float(logs.counts["ERROR"] + logs.counts["CRITICAL"]), "records",
         f"{logs.counts['WARNING']} warnings; " + ("; ".join(logs.first) or "nothing logged")),
        ("filter resets", float(status.reset_counter), "", ""),
    ]
    if camera:
        frames_used = status.counts["camera"]["used"] if "camera" in status.counts else 0
        rows.append(("landmarks in the map (max over the run)", float(max(s[5] for s in samples)), "landmarks",
                     f"cap estimator.camera.max_landmarks = {camera_options(cfg).map.max_landmarks}; "
                     f"{frames_used} frames used of {len(frames)}"))
    return rows + [(f"  memory at {s[0] / 60:.0f} min", s[1], "MB",
                    f"history {s[2]} (capacity {s[3]})" + (f", landmarks {s[5]}" if camera else "")) for s in samples]


def bench_soak_camera() -> list[Row]:
    """One hour of IMU+camera+GPS (landfill, ORB) through the runtime: memory, landmarks, history stay bounded."""
    return bench_runtime_hour(camera=True)
