"""The ``<prefix>/pose`` document (INTERFACES.md, "Out: Zenoh"): the reference dictionary and its JSON text
written straight from the pose, for every IMU sample.

:func:`pose_message` is the reference: the document as a dictionary, which ``json.dumps`` writes.
:class:`PoseJson` writes the same bytes without building the dictionary, because the pose leaves on
the event loop for every IMU sample: the message has a fixed shape, so one preformatted template is
filled with the numbers. Python's JSON writes a finite float as ``repr`` does, so does ``%s``; a
number that is not finite (null in the document) sends the pose through the reference instead. What
is left is mostly the 49 ``repr``s of the numbers themselves, which the format asks for (a shortest
round-trip ``repr`` of a 17-digit double costs about a microsecond here). 36 of them are the covariance,
which the fusion core computes for the next pose after the previous one has left: :meth:`PoseJson.prepare`
writes its text then, off the pose path, and the pose that carries that very array uses it. A test holds
the two to the same bytes for every kind of pose; ``vtolpose bench --only pose-encoding`` measures both.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from vtolpose.estimator import OutputPose
from vtolpose.service.runtime.status import heading_weak, pose_quality

Origin = tuple[float, float, float] | None


def pose_status(pose: OutputPose, quality: int, diagonal: list[float] | None = None) -> str:
    """``ok`` or why not; ``diagonal``: ``pose.cov9``'s diagonal as a list, when the caller has it."""
    if not pose.position_initialized:
        return "no_position"
    if not pose.heading_aligned:
        return "heading_unaligned"
    if heading_weak(pose, diagonal):
        return "heading_weak"
    return "ok" if quality > 0 else "poor"


def _vector(values: np.ndarray) -> list:
    """A flat array as a list of plain floats; non-finite numbers become null (JSON has no NaN)."""
    out = values.tolist()
    if math.isfinite(sum(out)):
        return out
    return [x if math.isfinite(x) else None for x in out]


def origin_json(origin: Origin) -> dict | None:
    return None if origin is None else {"lat": origin[0], "lon": origin[1], "alt": origin[2]}


def pose_message(pose: OutputPose, seq: int, origin: Origin) -> dict[str, Any]:
    """The ``<prefix>/pose`` document (INTERFACES.md), plus ``fused``, ``kind`` and ``quality``."""
    quality = pose_quality(pose)
    return {
        "t_ns": pose.t_ns, "frame": "NED", "origin": origin_json(origin),
        "p": _vector(pose.p), "q": _vector(pose.q), "v": _vector(pose.v), "w": _vector(pose.omega_b),
        "cov": _vector(pose.pose_cov.reshape(36)), "status": pose_status(pose, quality),
        "seq": seq, "fused": pose.fused, "kind": "filtered" if pose.fused else "predicted", "quality": quality,
    }


def _numbers(count: int) -> str:
    return "[" + ", ".join(["%s"] * count) + "]"


# json.dumps(pose_message(...)) with its numbers left out: the same keys, order and separators; the
# covariance's list is written on its own (_COVARIANCE) and goes in whole.
_TEMPLATE = ('{"t_ns": %d, "frame": "NED", "origin": %s, '
             f'"p": {_numbers(3)}, "q": {_numbers(4)}, "v": {_numbers(3)}, "w": {_numbers(3)}, "cov": %s, '
             '"status": "%s", "seq": %d, "fused": %s, "kind": "%s", "quality": %d}')
_COVARIANCE = _numbers(36)
_UNSET = object()


class PoseJson:
    """``json.dumps(pose_message(pose, seq, origin))``, the same bytes, in fewer calls.

    The origin's text is kept while the origin callable hands back the same object (a GPS fixes it
    once); the covariance's, from :meth:`prepare`, while poses carry the array it was written from."""

    __slots__ = ("_origin", "_origin_text", "_cov", "_cov_text", "prepared_used")

    def __init__(self) -> None:
        self._origin: object = _UNSET
        self._origin_text = "null"
        self._cov: np.ndarray | None = None
        self._cov_text = ""
        self.prepared_used = 0  # poses whose covariance text was written ahead (bench and tests read it)

    def prepare(self, pose_cov: np.ndarray | None) -> None:
        """Write the text of ``pose_cov`` (the next pose's, as the fusion core has it ready) now, off the
        pose path. Poses are never changed in place, so a pose that carries this very array has this text;
        any other covariance is written when its pose comes. Not finite: nothing kept (the reference writes it)."""
        if pose_cov is None or pose_cov is self._cov:
            return
        numbers = pose_cov.reshape(36).tolist()
        if math.isfinite(sum(numbers)):
            self._cov, self._cov_text = pose_cov, _COVARIANCE % tuple(numbers)
        else:
            self._cov = None

    def __call__(self, pose: OutputPose, seq: int, origin: Origin) -> str:
        numbers = pose.p.tolist() + pose.q.tolist() + pose.v.tolist() + pose.omega_b.tolist()
        cov = pose.pose_cov
        if cov is self._cov:
            cov_text = self._cov_text
            self.prepared_used += 1
            finite = math.isfinite(sum(numbers))
        else:
            cov_numbers = cov.reshape(36).tolist()
            finite = math.isfinite(sum(numbers) + sum(cov_numbers))
            cov_text = _COVARIANCE % tuple(cov_numbers) if finite else ""
        if not finite:  # a null in the document (or merely a sum that overflowed)
            return json.dumps(pose_message(pose, seq, origin))
        if origin is not self._origin:
            self._origin_text, self._origin = json.dumps(origin_json(origin)), origin
        diagonal = pose.cov9.diagonal().tolist()
        quality = pose_quality(pose, diagonal)
        fused = pose.fused
        return _TEMPLATE % (pose.t_ns, self._origin_text, *numbers, cov_text, pose_status(pose, quality, diagonal), seq,
                            "true" if fused else "false", "filtered" if fused else "predicted", quality)
