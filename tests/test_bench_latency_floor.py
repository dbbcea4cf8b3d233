"""The latency-floor bench's stand-ins: each removes the work it names and nothing else, on its runtime only."""

import socket

import pytest

from conftest import free_port

ODOMETRY_ID = 331


def _odometry_payloads(sock: socket.socket) -> list[bytes]:
    """The ODOMETRY payloads of the MAVLink v2 datagrams waiting on ``sock``."""
    payloads = []
    while True:
        try:
            data = sock.recv(4096)
        except BlockingIOError:
            return payloads
        assert data[0] == 0xFD
        if int.from_bytes(data[7:10], "little") == ODOMETRY_ID:
            payloads.append(data[10:10 + data[1]])


@pytest.fixture(scope="module")
def book(tmp_path_factory):
    from vtolpose.drivers.files.dataset import Dataset
    from vtolpose.drivers.simulator import simulate_flight
    from vtolpose.drivers.simulator.export import write_flight

    root = tmp_path_factory.mktemp("floor") / "book"
    write_flight(simulate_flight("book", 6.0, 3), root)
    dataset = Dataset.open(root)
    imu, gps = dataset.imu(), dataset.gps()
    from vtolpose.estimator import GpsFix, ImuSample

    samples = [ImuSample(int(t), g, a) for t, g, a in zip(imu.t_ns, imu.gyro, imu.accel)]
    samples += [GpsFix(int(t), p, float(h), float(v)) for t, p, h, v in zip(gps.t_ns, gps.p_ned, gps.sigma_h, gps.sigma_v)]
    samples.sort(key=lambda s: (s.t_ns, isinstance(s, GpsFix)))
    return dataset.calibration, samples


def _runtime_after_warm_up(book, sink_port: int):
    from vtolpose.config import load_config
    from vtolpose.service.runtime.daemon import build_runtime

    calibration, samples = book
    cfg = load_config(None, {"outputs": {
        "mavlink": {"enabled": True, "url": f"udpout:127.0.0.1:{sink_port}", "rate_hz": 1000.0},
        "zenoh": {"enabled": True, "listen": [f"tcp/127.0.0.1:{free_port()}"], "multicast_scouting": False}}})
    runtime = build_runtime(cfg, calibration)
    half = len(samples) // 2
    for sample in samples[:half]:
        runtime.handle(sample)
    assert runtime.fusion.output() is not None
    return runtime, samples[half:]


def _publish_rest(runtime, rest, sink: socket.socket) -> tuple[list, list[bytes]]:
    """The rest of the samples through the runtime with its MAVLink output open: the poses it made, the payloads sent."""
    from vtolpose.estimator import ImuSample

    mavlink = next(o for o in runtime.outputs if o.name == "mavlink")
    mavlink.open()
    poses = []
    try:
        for sample in rest:
            runtime.handle(sample)
            if isinstance(sample, ImuSample):
                poses.append(runtime.fusion.output())
    finally:
        mavlink.close()
    return poses, _odometry_payloads(sink)


@pytest.fixture()
def sink():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", free_port(socket.SOCK_DGRAM)))
    sock.setblocking(False)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    yield sock
    sock.close()


@pytest.mark.parametrize("parts", [(), ("encodings",), ("encodings", "prediction")])
def test_each_stand_in_removes_its_work_and_the_samples_still_reach_the_filter(book, sink, parts):
    from vtolpose.service.bench.latency_floor import stand_in

    runtime, rest = _runtime_after_warm_up(book, sink.getsockname()[1])
    zenoh_out = next(o for o in runtime.outputs if o.name == "zenoh")
    est = runtime.est
    t_before, received_before = est.state.t_ns, runtime.fusion.counts["imu"].received
    if parts:
        stand_in(runtime, parts)
    poses, payloads = _publish_rest(runtime, rest, sink)

    imu_count = len(poses)
    assert len(payloads) == imu_count > 100  # a pose went out for every sample
    assert runtime.fusion.counts["imu"].received == received_before + imu_count  # every sample still queued ...
    assert est.state.t_ns > t_before + 1_000_000_000  # ... and fused by the filter
    documents = {zenoh_out._pose_json(pose, 1, None) for pose in poses[:20]}
    assert (len(set(payloads)) == 1) is ("encodings" in parts)  # the first pose's bytes again, or each its own
    assert (len(documents) == 1) is ("encodings" in parts)
    assert (len({id(pose) for pose in poses}) == 1) is ("prediction" in parts)  # the first pose again, or predicted
    stepped_to = runtime.fusion.detached().pred.t_ns  # the output predictor steps to each sample, or stands still
    assert (stepped_to < runtime.fusion.newest_imu_t_ns) is ("prediction" in parts)


def test_a_stand_in_not_known_or_before_the_start_is_refused(book, sink):
    from vtolpose.config import load_config
    from vtolpose.service.bench.latency_floor import stand_in
    from vtolpose.service.runtime.daemon import build_runtime

    runtime, _ = _runtime_after_warm_up(book, sink.getsockname()[1])
    with pytest.raises(ValueError, match="unknown stand-in.*'encoder'"):
        stand_in(runtime, ("encoder",))
    cold = build_runtime(load_config(None, {}), book[0])
    with pytest.raises(ValueError, match="once the filter has started"):
        stand_in(cold, ("prediction",))
