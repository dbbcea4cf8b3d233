"""The estimator's modes: what its position and its heading are referenced to, as two small state
machines with every legal transition in one table.

``FilterMode`` says where the position stands: no state yet (the IMU's window filling, or the
visual-inertial start's), running without a reference yet, the camera's own frame, a GPS joining such a
frame, or the GPS's world frame. A running filter is only ever one that was handed a complete start
(``estimator/start.py``): there is no half-started mode. ``HeadingMode`` says whether the heading is unknown (a frame of
arbitrary yaw, levelled by gravity), known (dataset or operator) or placed from GPS by the heading
hypotheses. The estimator changes either only through :meth:`ModeMachine.fire` with an event of
:data:`TRANSITIONS`; a pair that is not in the table is a bug and raises. The conditions are the
estimator's (``estimator/filter.py``); the table states them so that the docs can draw the machine
(:func:`mermaid`) and a test can walk every edge.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum


class FilterMode(Enum):
    WAITING = "waiting"  # no state yet: the IMU's start window fills
    INITIALISING = "initialising"  # no state yet: moving, a camera, no GPS; the visual-inertial window fills
    UNREFERENCED = "unreferenced"  # running, no position reference yet: no fix, no camera frame used
    LOCAL = "local"  # the camera's own frame: origin (and an unknown heading) where the camera started
    JOINING = "joining"  # a GPS joins the camera's frame: its first second of fixes is collected
    GPS = "gps"  # the world frame, placed by GPS

    @property
    def initialised(self) -> bool:
        """A running filter exists (nothing is published before)."""
        return self not in (FilterMode.WAITING, FilterMode.INITIALISING)

    @property
    def joining(self) -> bool:
        return self is FilterMode.JOINING

    @property
    def local_position(self) -> bool:
        """Position (and, unless known, heading) in the camera's own frame: no GPS has been heard."""
        return self is FilterMode.LOCAL

    @property
    def position_from_gps(self) -> bool:
        return self is FilterMode.GPS


class HeadingMode(Enum):
    UNKNOWN = "unknown"  # a frame of arbitrary yaw: gravity levels it, the hypotheses search once a GPS is heard
    KNOWN = "known"  # given by the dataset or the operator
    PLACED = "placed"  # placed from GPS by the heading hypotheses

    @property
    def aligned(self) -> bool:
        return self is not HeadingMode.UNKNOWN


def heading_aligned(mode: FilterMode, heading: HeadingMode) -> bool:
    """A running filter whose heading is known or placed (before the start there is no heading to speak of)."""
    return mode.initialised and heading.aligned


class ModeEvent(Enum):
    START_BLIND = "start, moving, camera only"
    START_PLACED = "start, still, a recent fix"
    START_UNREFERENCED = "start, otherwise"
    VISUAL_START = "visual-inertial start"
    CAMERA_USED = "first camera frame used"
    CAMERA_LOST = "camera lost"
    GPS_HEARD = "GPS fix"
    GPS_JOINED = "GPS joined"
    HEADING_PLACED = "heading placed"
    HEADING_SEARCH = "heading searched again"
    RELEVEL = "attitude levelled again"


@dataclass(frozen=True, slots=True)
class Transition:
    source: FilterMode | HeadingMode
    event: ModeEvent
    target: FilterMode | HeadingMode
    condition: str


F, H, E = FilterMode, HeadingMode, ModeEvent
TRANSITIONS: tuple[Transition, ...] = (
    Transition(F.WAITING, E.START_BLIND, F.INITIALISING,
               "moving at the start, camera frames received, the visual start enabled, no GPS heard: no state yet"),
    Transition(F.WAITING, E.START_PLACED, F.GPS, "still at the start and a fix within the last second"),
    Transition(F.WAITING, E.START_UNREFERENCED, F.UNREFERENCED, "any other start"),
    Transition(F.WAITING, E.VISUAL_START, F.LOCAL, "the visual-inertial window converged before the IMU's start"),
    Transition(F.INITIALISING, E.VISUAL_START, F.LOCAL, "the visual-inertial window converged"),
    Transition(F.INITIALISING, E.START_UNREFERENCED, F.UNREFERENCED,
               "a second of GPS fixes heard first: the moving start the GPS gives, from the IMU's latest window"),
    Transition(F.UNREFERENCED, E.CAMERA_USED, F.LOCAL, "a camera frame fused and no GPS heard"),
    Transition(F.UNREFERENCED, E.GPS_HEARD, F.GPS, "a usable fix: the position from it"),
    Transition(F.LOCAL, E.GPS_HEARD, F.JOINING, "a usable fix"),
    Transition(F.LOCAL, E.CAMERA_LOST, F.INITIALISING,
               "camera innovations out of band, the visual start enabled: the filter is dropped, the visual start again"),
    Transition(F.JOINING, E.GPS_JOINED, F.GPS, "a second of fixes: velocity from them, position from the last"),
    Transition(H.UNKNOWN, E.HEADING_PLACED, H.PLACED, "one hypothesis outweighs the others and its sigma is small"),
    Transition(H.PLACED, E.HEADING_SEARCH, H.UNKNOWN, "every fix refused for the reset time: the placed heading suspected"),
    Transition(H.PLACED, E.RELEVEL, H.UNKNOWN, "fixes still refused right after a GPS reset"),
    Transition(H.KNOWN, E.RELEVEL, H.UNKNOWN, "fixes still refused right after a GPS reset"),
    Transition(H.UNKNOWN, E.RELEVEL, H.UNKNOWN, "fixes still refused right after a GPS reset"),
)
_TABLE = {(t.source, t.event): t for t in TRANSITIONS}


class IllegalTransition(RuntimeError):
    """An event the current mode has no edge for: the estimator's logic and the table disagree."""


class ModeMachine:
    """The two modes and the one place that changes them."""

    __slots__ = ("mode", "heading", "heading_aligned")

    def __init__(self, heading_known: bool) -> None:
        self.mode = FilterMode.WAITING
        self.heading = HeadingMode.KNOWN if heading_known else HeadingMode.UNKNOWN
        self.heading_aligned = False  # heading_aligned(mode, heading), kept with them: asked for every sample

    def fire(self, event: ModeEvent) -> Transition:
        """Take the edge ``event`` leaves from the mode it concerns; raises :class:`IllegalTransition` if none."""
        edge = _TABLE.get((self.mode, event)) or _TABLE.get((self.heading, event))
        if edge is None:
            raise IllegalTransition(f"{event.value!r} in mode {self.mode.value}, heading {self.heading.value}")
        if isinstance(edge.target, FilterMode):
            self.mode = edge.target
        else:
            self.heading = edge.target
        self.heading_aligned = heading_aligned(self.mode, self.heading)
        return edge

    def can(self, event: ModeEvent) -> bool:
        return (self.mode, event) in _TABLE or (self.heading, event) in _TABLE


def mermaid() -> str:
    """Both machines as Mermaid state diagrams, each edge labelled with its event and condition."""
    lines = []
    for kind, title in ((FilterMode, "Position reference (FilterMode)"), (HeadingMode, "Heading (HeadingMode)")):
        start = FilterMode.WAITING if kind is FilterMode else None
        lines += [f"**{title}**", "", "```mermaid", "stateDiagram-v2"]
        if start is not None:
            lines.append(f"    [*] --> {start.value}")
        else:
            lines += ["    [*] --> known: heading given", "    [*] --> unknown: no heading given"]
        for t in TRANSITIONS:
            if isinstance(t.source, kind):
                lines.append(f"    {t.source.value} --> {t.target.value}: {t.event.value} ({t.condition})")
        lines += ["```", ""]
    return "\n".join(lines).rstrip() + "\n"
