"""The pose message written straight from the pose (PoseJson) is, byte for byte, ``json.dumps(pose_message(...))``:
the wire format of ``<prefix>/pose`` is an interface (INTERFACES.md) that mappers parse."""

import dataclasses
import itertools
import json
import math
import threading
import time

import numpy as np
import pytest
import zenoh

from vtolpose.estimator.core.rotation import quat_exp, quat_from_euler
from vtolpose.estimator.fusion import OutputPose
from vtolpose.estimator.pose_history import PoseHistory
from vtolpose.service.outputs.pose_json import PoseJson, pose_message
from vtolpose.service.outputs.zenoh import ZenohOutput
from vtolpose.service.outputs.zenoh_session import ZenohSettings

from conftest import free_port

POSE = [0, 1, 2, 6, 7, 8]
FLAGS = ("heading_aligned", "position_initialized", "local_position", "fused")
SPECIAL = (math.nan, math.inf, -math.inf, 0.0, -0.0, 1e-300, 5e-324, 1.7976931348623157e308, 1e16, 1e-5, 123456789.0)


def random_pose(rng: np.random.Generator, flags: dict[str, bool], cap: int, special: float | None) -> OutputPose:
    """A pose with a random covariance (not symmetric to the last bit, as the filter's), its magnitudes spread
    over many decades; ``special`` put in one random number of it (a vector, the covariance or its diagonal)."""
    a = rng.normal(size=(9, 9)) * 10.0 ** rng.uniform(-5, 1)
    cov9 = a @ a.T
    cov9 += rng.normal(size=(9, 9)) * 1e-20  # the filter's covariance is symmetric only to rounding
    cov9[8, 8] = 10.0 ** rng.uniform(-8, 0)  # the heading's variance: weak or not
    vectors = [rng.normal(size=3) * 10.0 ** rng.uniform(-3, 4), quat_from_euler(*rng.uniform(-3, 3, 3)),
               rng.normal(size=3) * 10.0 ** rng.uniform(-3, 2), rng.normal(size=3) * 10.0 ** rng.uniform(-4, 0)]
    if special is not None:
        where = int(rng.integers(0, 3))
        if where == 0:
            target = vectors[int(rng.integers(0, 4))]
            target[int(rng.integers(0, len(target)))] = special
        elif where == 1:
            cov9[POSE[int(rng.integers(0, 6))], POSE[int(rng.integers(0, 6))]] = special
        else:
            cov9[int(rng.integers(0, 9)), int(rng.integers(0, 9))] = special
    t_ns = int(rng.integers(0, 1 << 62))
    return OutputPose(t_ns, vectors[0], vectors[2], vectors[1], vectors[3], cov9, cov9[np.ix_(POSE, POSE)],
                      np.full(3, 1e-6), flags["heading_aligned"], flags["position_initialized"], 3,
                      t_ns if flags["fused"] else t_ns - int(rng.integers(1, 10**9)), cap, flags["local_position"])


def test_every_kind_of_pose_is_written_as_json_dumps_writes_it():
    rng = np.random.default_rng(16)
    encode = PoseJson()  # one writer for all: its kept origin must follow every change
    origins = [None, (58.43, 15.68, 60.0), (58.43, 15.68, 60.0), (-33.9, 151.2, -12.5), (0, 0, 0), (math.nan, 0.0, 1e308)]
    statuses, qualities, fallbacks = set(), set(), 0
    for values in itertools.product((False, True), repeat=len(FLAGS)):
        flags = dict(zip(FLAGS, values))
        for cap, special in itertools.product((100, 20, 0), (None,) + SPECIAL):
            for _ in range(2):
                pose = random_pose(rng, flags, cap, special)
                origin = origins[int(rng.integers(0, len(origins)))]
                seq = int(rng.integers(0, 1 << 40))
                expected = json.dumps(pose_message(pose, seq, origin))
                assert encode(pose, seq, origin) == expected, (flags, cap, special, origin)
                document = json.loads(expected)
                statuses.add(document["status"])
                qualities.add(document["quality"])
                fallbacks += "null" in expected.partition('"p"')[2]  # a number that is not finite: the reference's path
    # The poses above covered every status, capped and uncapped qualities, and both of the writer's paths.
    assert statuses == {"ok", "poor", "heading_weak", "heading_unaligned", "no_position"}
    assert {0, 20} <= qualities and max(qualities) > 20
    assert 0 < fallbacks < 0.9 * 2 * 3 * (1 + len(SPECIAL)) * 2 ** len(FLAGS)


def test_a_changed_or_equal_but_new_origin_is_written_afresh():
    """The writer keeps the origin's text while it is handed the same object; any other object is written anew
    (even an equal one: 1 and 1.0 are equal but written differently)."""
    pose = random_pose(np.random.default_rng(3), dict.fromkeys(FLAGS, True), 100, None)
    encode = PoseJson()
    for origin in [(1.0, 2.0, 3.0), (1, 2, 3), None, (1.0, 2.0, 3.0), (1.0, 2.0, 3.5)]:
        assert encode(pose, 7, origin) == json.dumps(pose_message(pose, 7, origin)), origin


def test_the_published_bytes_and_sequence_numbers_on_loopback():
    """What a subscriber receives: the reference's bytes, each under its ``seq`` as Zenoh's source sequence number
    and the publisher's own id."""
    port, origin = free_port(), (58.43, 15.68, 60.0)
    out = ZenohOutput(ZenohSettings("peer", [f"tcp/127.0.0.1:{port}"], [], False), "test/vehicle", PoseHistory(10.0),
                      threading.Lock(), lambda: origin)
    out.open()
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    session = zenoh.open(config)
    got: list[tuple[bytes, int, str]] = []
    subscriber = session.declare_subscriber("test/vehicle/pose", lambda s: got.append(
        (s.payload.to_bytes(), s.source_info.source_sn, str(s.source_info.source_id))))
    try:
        rng = np.random.default_rng(5)
        poses = [random_pose(rng, dict.fromkeys(FLAGS, True), 100, None) for _ in range(3)]
        deadline = time.monotonic() + 5.0
        while not got and time.monotonic() < deadline:  # until the subscription has reached the publisher
            out.publish(poses[0])
            time.sleep(0.05)
        assert got, "the subscription never reached the publisher"
        first = out._seq
        for pose in poses:
            out.publish(pose)
        deadline = time.monotonic() + 5.0
        while got[-1][1] < first + len(poses) and time.monotonic() < deadline:
            time.sleep(0.01)
        received = {sn: (payload, source) for payload, sn, source in got}
        for k, pose in enumerate(poses, start=first + 1):
            assert received[k] == (json.dumps(pose_message(pose, k, origin)).encode(), str(out._pose_pub.id)), k
    finally:
        subscriber.undeclare()
        session.close()
        out.close()


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_a_pose_with_a_number_that_is_not_finite_is_written_with_null(value):
    pose = random_pose(np.random.default_rng(9), dict.fromkeys(FLAGS, True), 100, None)
    pose.p[1] = value
    text = PoseJson()(pose, 1, None)
    assert text == json.dumps(pose_message(pose, 1, None)) and json.loads(text)["p"][1] is None


def test_the_attitude_is_written_scalar_first_as_the_pose_holds_it():
    """``q`` is [w, x, y, z], body→NED (INTERFACES.md): for a turn of 2.4 rad about a tilted axis the document
    holds cos(θ/2) first, then sin(θ/2) times the axis, in both writers (a mapper reading x, y, z, w would
    place every LIDAR return with the wrong attitude)."""
    axis = np.array([0.36, -0.48, 0.8])
    angle = 2.4
    pose = random_pose(np.random.default_rng(3), dict.fromkeys(FLAGS, True), 100, None)
    pose = dataclasses.replace(pose, q=quat_exp(angle * axis))
    expected = [math.cos(angle / 2), *(math.sin(angle / 2) * axis)]
    for text in (PoseJson()(pose, 1, None), json.dumps(pose_message(pose, 1, None))):
        q = json.loads(text)["q"]
        np.testing.assert_allclose(q, expected, rtol=0, atol=1e-15)
        assert q == pose.q.tolist()


def test_a_covariance_written_ahead_is_used_only_by_the_pose_that_carries_that_very_array():
    """``prepare`` writes the next pose's covariance off the pose path; the pose carrying that array gets the same
    bytes as the reference, and any other pose (an equal copy, another covariance, a prepared one that was not
    finite) is written from its own numbers."""
    rng = np.random.default_rng(21)
    encode = PoseJson()
    for k in range(40):
        pose = random_pose(rng, dict.fromkeys(FLAGS, True), 100, SPECIAL[k % len(SPECIAL)] if k % 4 == 3 else None)
        encode.prepare(pose.pose_cov)
        before = encode.prepared_used
        assert encode(pose, k, None) == json.dumps(pose_message(pose, k, None)), k
        assert encode.prepared_used == before + bool(np.isfinite(pose.pose_cov).all())
    # A copy of the prepared array, or another covariance: their own numbers, never the kept text.
    pose = random_pose(rng, dict.fromkeys(FLAGS, True), 100, None)
    encode.prepare(pose.pose_cov)
    used = encode.prepared_used
    for other in (pose.pose_cov.copy(), pose.pose_cov * 2.0):
        changed = dataclasses.replace(pose, pose_cov=other)
        assert encode(changed, 1, None) == json.dumps(pose_message(changed, 1, None))
    assert encode.prepared_used == used
    # A pose whose prepared covariance is not finite is the reference's (nulls), with nothing kept for it.
    bad = pose.pose_cov.copy()
    bad[2, 3] = math.nan
    changed = dataclasses.replace(pose, pose_cov=bad)
    encode.prepare(bad)
    assert encode(changed, 2, None) == json.dumps(pose_message(changed, 2, None)) and encode.prepared_used == used
