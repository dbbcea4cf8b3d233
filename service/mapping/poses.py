"""Where the mapper's poses come from: a whole trajectory in memory, or the service over Zenoh, per scan.

A pose source is called once per scan with the times of its returns and gives one body pose
(NED position, body→NED quaternion) per return, interpolated at that return's own time. It
raises ``OutsideHistory`` when it has no pose for the scan (before the trajectory starts, after
it ends, or already dropped from the service's history), and ``TimeoutError`` when the service
has not reached the scan within the wait.
"""

from __future__ import annotations

import json
import threading
import time
from typing import Callable

import numpy as np

from vtolpose.client import OutsideHistory, PoseClient, PoseUnavailable, PoseWindow
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.files.tum import read_tum
from vtolpose.estimator import quat_to_rot

PoseSource = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]

# What a live mapper can wait for before placing a scan, worst first (docs/mapping.md).
WAIT_KINDS = ("filtered", "smoothed")


def trajectory_window(t_ns: np.ndarray, p: np.ndarray, q: np.ndarray) -> PoseWindow:
    """A whole trajectory as the window type the client returns (velocity and rate unused: zero)."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    if t_ns.size < 2 or np.any(np.diff(t_ns) <= 0):
        raise ValueError("a trajectory for mapping needs at least two poses with increasing times")
    zeros = np.zeros((t_ns.size, 3))
    return PoseWindow(t_ns, np.asarray(p, dtype=float), np.asarray(q, dtype=float), zeros, zeros,
                      np.ones(t_ns.size, dtype=bool))


def file_window(path: str) -> PoseWindow:
    """A TUM trajectory (what ``replay --out`` writes) or a EuRoC truth CSV with attitude."""
    t, p, q = read_tum(path)
    if q is None:
        raise ValueError(f"{path}: positions only; placing LIDAR returns needs the attitude too")
    return trajectory_window(t, p, q)


def truth_window(dataset: Dataset) -> PoseWindow:
    """The dataset's truth as body-origin poses (its reference point ``truth.point_b`` moved back to the body origin)."""
    truth = dataset.truth()
    if truth is None or truth.q is None:
        raise ValueError(f"{dataset.root}: no truth with attitude (mav0/state_groundtruth_estimate0) to map with")
    p = truth.p - quat_to_rot(truth.q) @ dataset.calibration.truth_point_b
    return trajectory_window(truth.t_ns, p, truth.q)


def sub_window(window: PoseWindow, t0_ns: int, t1_ns: int) -> PoseWindow:
    """The poses of ``window`` a query for ``[t0, t1]`` would get: those inside plus the nearest one beyond each end."""
    lo = max(int(np.searchsorted(window.t_ns, t0_ns, side="right")) - 1, 0)
    hi = min(int(np.searchsorted(window.t_ns, t1_ns, side="left")) + 1, len(window))
    return PoseWindow(window.t_ns[lo:hi], window.p[lo:hi], window.q[lo:hi], window.v[lo:hi], window.w[lo:hi],
                      window.fused[lo:hi])


def window_poses(window: PoseWindow) -> PoseSource:
    """Every return's pose interpolated from one window held in memory (cut to the scan first, as a query would be)."""
    def poses(t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return sub_window(window, int(t_ns[0]), int(t_ns[-1])).interpolate(t_ns)

    return poses


def mixed_poses(position: PoseWindow, attitude: PoseWindow) -> PoseSource:
    """Positions from one trajectory, attitudes from another: what each part of a pose costs the map."""
    at_position, at_attitude = window_poses(position), window_poses(attitude)

    def poses(t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return at_position(t_ns)[0], at_attitude(t_ns)[1]

    return poses


def one_pose_per_scan(window: PoseWindow) -> PoseSource:
    """The pose at each scan's first return used for the whole scan: what ignoring return times costs."""
    at = window_poses(window)

    def poses(t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p, q = at(t_ns[:1])
        n = len(t_ns)
        return np.repeat(p, n, axis=0), np.repeat(q, n, axis=0)

    return poses


class ZenohPoses:
    """Poses from a running service: one ``trajectory()`` query per scan, interpolated per return.

    A scan is placed once the service's history covers it with poses of at least ``kind``:
    ``filtered`` takes them once fused (filtered, or smoothed if the fixed lag has already passed;
    ~0.2 s behind), ``smoothed`` waits until every pose over the scan is smoothed (the daemon's
    fixed-lag history, ~2-3 s behind). Until then the query is repeated every ``poll_s``. Where the
    service's history starts comes from its status document (``<prefix>/status``, once a second: the
    history's time span); a scan is skipped as too old only when that span starts after it. An answer
    refused for another reason (a second session claiming the prefix, say) is asked again until the
    wait ends.
    """

    def __init__(self, client: PoseClient, wait_s: float = 10.0, poll_s: float = 0.05, kind: str = "filtered") -> None:
        if kind not in WAIT_KINDS:
            raise ValueError(f"kind {kind!r}: a mapper waits for one of {', '.join(WAIT_KINDS)}")
        self.client = client
        self.wait_s = wait_s
        self.poll_s = poll_s
        self.kind = kind
        self.queries = 0
        self._oldest_ns: int | None = None  # where the service's history starts, by its last status
        self._lock = threading.Lock()
        self._status = client.session.declare_subscriber(f"{client.prefix}/status", self._on_status)

    def close(self) -> None:
        self._status.undeclare()

    def _on_status(self, sample) -> None:
        try:
            span = json.loads(sample.payload.to_string())["history"]
            oldest = span["from_t_ns"]
        except (ValueError, KeyError, TypeError):
            return  # a status without the history's span says nothing about it
        if isinstance(oldest, int):
            with self._lock:
                self._oldest_ns = oldest

    def _oldest(self) -> int | None:
        with self._lock:
            return self._oldest_ns

    def _final(self, window: PoseWindow) -> bool:
        """Whether every pose of the answer is of the kind waited for."""
        if self.kind == "filtered":
            return bool(window.fused.all())
        if window.kind is None:
            raise ValueError("the service's trajectory answers carry no pose kinds (an older vtolpose): "
                             "it cannot say which poses are smoothed; map with kind 'filtered'")
        return bool(np.all(window.kind == "smoothed"))

    def __call__(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t0, t1 = int(t_ns[0]), int(t_ns[-1])
        deadline = time.monotonic() + self.wait_s
        while True:
            self.queries += 1
            try:
                window = self.client.trajectory(t0, t1)
            except TimeoutError:  # no answer (the service not up yet, a link down): keep asking until the wait ends
                pass
            except PoseUnavailable:  # too old, not reached yet, or refused for now (two sessions claiming the prefix)
                oldest = self._oldest()
                if oldest is not None and oldest > t1:
                    raise OutsideHistory(f"scan at t_ns={t0}..{t1} is older than the service's history") from None
            else:
                if window.t_ns[0] > t0:
                    raise OutsideHistory(f"scan at t_ns={t0}..{t1} starts before the service's history")
                if window.t_ns[-1] >= t1 and self._final(window):
                    return window.interpolate(t_ns)
            if time.monotonic() > deadline:
                hint = ("is the service running, has it reached this scan" +
                        (", and does it smooth (smoothing.fixed_lag_s > 0)?)" if self.kind == "smoothed" else "?)"))
                raise TimeoutError(f"no {self.kind} poses for the scan at t_ns={t0}..{t1} within {self.wait_s:g} s "
                                   f"({hint}")
            time.sleep(self.poll_s)
