"""``--fault`` specs parsed, and the options that take them: light, so a command's ``--help`` loads no numpy
(the faults themselves are played by ``vtolpose.service.replay.faults``, whose docstring lists the specs)."""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from typing import Any, Iterable

# kind -> (the sensor it touches, its spec after the kind, for error messages)
FAULT_KINDS: dict[str, tuple[str | None, str]] = {
    "gps-off": ("gps", "START:DURATION"),
    "camera-off": ("camera", "START:DURATION"),
    "imu-gap": ("imu", "START:DURATION"),
    "gps-jump": ("gps", "START:DN,DE,DD[:DURATION]"),
    "gps-multipath": ("gps", "START:DURATION:SIGMA:RATE"),
    "gps-sigma": ("gps", "START:DURATION:SIGMA"),
    "camera-freeze": ("camera", "START:DURATION"),
    "clock-step": (None, "T:STEP"),
    "nan": (None, "SENSOR:START:DURATION"),
}
NAN_SENSORS = ("imu", "gps")
MAX_CLOCK_STEP_S = 3600.0
DEFAULT_JUMP_DURATION_S = 1.0


class FaultError(ValueError):
    """A fault spec that cannot be played; the message names the spec and the part at fault."""


@dataclass(frozen=True, slots=True)
class Fault:
    """One parsed ``--fault`` spec. Window ``[start_s, start_s + duration_s)`` in data seconds."""

    kind: str
    sensor: str | None  # the stream it touches; None: every stream (clock-step)
    start_s: float
    duration_s: float = math.inf
    offset_m: tuple[float, float, float] | None = None  # gps-jump
    sigma_m: float = 0.0  # gps-multipath
    rate: float = 0.0  # gps-multipath: fraction of fixes hit
    step_s: float = 0.0  # clock-step
    spec: str = ""

    def covers(self, t_s: float) -> bool:
        return self.start_s <= t_s < self.start_s + self.duration_s

    def describe(self) -> dict[str, Any]:
        doc: dict[str, Any] = {"spec": self.spec, "kind": self.kind, "sensor": self.sensor or "all",
                               "start_s": self.start_s}
        if math.isfinite(self.duration_s):
            doc["duration_s"] = self.duration_s
        if self.offset_m is not None:
            doc["offset_m"] = list(self.offset_m)
        if self.kind == "gps-multipath":
            doc.update(sigma_m=self.sigma_m, rate=self.rate)
        if self.kind == "gps-sigma":
            doc["claimed_sigma_m"] = self.sigma_m
        if self.kind == "clock-step":
            doc["step_s"] = self.step_s
        return doc


def _number(spec: str, name: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise FaultError(f"--fault {spec!r}: {name} {text!r} is not a number") from None
    if not math.isfinite(value):
        raise FaultError(f"--fault {spec!r}: {name} {text!r} must be finite")
    return value


def _start(spec: str, text: str, name: str = "START") -> float:
    value = _number(spec, name, text)
    if value < 0.0:
        raise FaultError(f"--fault {spec!r}: {name} {text!r} must be >= 0 (seconds from the first sample)")
    return value


def _duration(spec: str, text: str) -> float:
    value = _number(spec, "DURATION", text)
    if value <= 0.0:
        raise FaultError(f"--fault {spec!r}: DURATION {text!r} must be greater than 0 s")
    return value


def parse_fault(spec: str) -> Fault:
    """One spec (see the module docstring); :class:`FaultError` names the part that is wrong."""
    if not isinstance(spec, str) or not spec.strip():
        raise FaultError(f"--fault {spec!r}: empty; expected KIND:..., KIND one of {', '.join(FAULT_KINDS)}")
    spec = spec.strip()
    kind, *parts = spec.split(":")
    if kind not in FAULT_KINDS:
        raise FaultError(f"--fault {spec!r}: unknown kind {kind!r}; choose from {', '.join(FAULT_KINDS)}")
    sensor, form = FAULT_KINDS[kind]
    lengths = {"gps-jump": (2, 3)}.get(kind, (form.count(":") + 1,))
    if len(parts) not in lengths:
        raise FaultError(f"--fault {spec!r}: {kind} takes {kind}:{form} ({len(parts)} part(s) given after the kind)")
    if kind in ("gps-off", "camera-off", "imu-gap", "camera-freeze"):
        return Fault(kind, sensor, _start(spec, parts[0]), _duration(spec, parts[1]), spec=spec)
    if kind == "gps-jump":
        values = parts[1].split(",")
        if len(values) != 3:
            raise FaultError(f"--fault {spec!r}: DN,DE,DD {parts[1]!r} must be three numbers [m], e.g. 20,0,0")
        offset = tuple(_number(spec, name, v) for name, v in zip(("DN", "DE", "DD"), values))
        duration = _duration(spec, parts[2]) if len(parts) == 3 else DEFAULT_JUMP_DURATION_S
        return Fault(kind, sensor, _start(spec, parts[0]), duration, offset_m=offset, spec=spec)
    if kind == "gps-multipath":
        sigma = _number(spec, "SIGMA", parts[2])
        if sigma <= 0.0:
            raise FaultError(f"--fault {spec!r}: SIGMA {parts[2]!r} must be greater than 0 m")
        rate = _number(spec, "RATE", parts[3])
        if not 0.0 < rate <= 1.0:
            raise FaultError(f"--fault {spec!r}: RATE {parts[3]!r} must be a fraction of fixes in (0, 1]")
        return Fault(kind, sensor, _start(spec, parts[0]), _duration(spec, parts[1]), sigma_m=sigma, rate=rate, spec=spec)
    if kind == "gps-sigma":
        sigma = _number(spec, "SIGMA", parts[2])
        if sigma <= 0.0:
            raise FaultError(f"--fault {spec!r}: SIGMA {parts[2]!r} must be greater than 0 m (the claim, however wrong)")
        return Fault(kind, sensor, _start(spec, parts[0]), _duration(spec, parts[1]), sigma_m=sigma, spec=spec)
    if kind == "clock-step":
        step = _number(spec, "STEP", parts[1])
        if step == 0.0 or abs(step) > MAX_CLOCK_STEP_S:
            raise FaultError(f"--fault {spec!r}: STEP {parts[1]!r} must be non-zero and at most {MAX_CLOCK_STEP_S:g} s")
        return Fault(kind, None, _start(spec, parts[0], "T"), math.inf, step_s=step, spec=spec)
    # nan:SENSOR:START:DURATION
    if parts[0] not in NAN_SENSORS:
        why = " (frames are 8-bit images: use camera-off or camera-freeze)" if parts[0] == "camera" else ""
        raise FaultError(f"--fault {spec!r}: SENSOR {parts[0]!r} must be one of {', '.join(NAN_SENSORS)}{why}")
    return Fault(kind, parts[0], _start(spec, parts[1]), _duration(spec, parts[2]), spec=spec)


def add_fault_options(p: argparse.ArgumentParser) -> None:
    """``--fault SPEC`` (repeatable) and ``--fault-seed N``: for every command that replays a dataset."""
    kinds = "; ".join(f"{kind}:{form}" for kind, (_, form) in FAULT_KINDS.items())
    p.add_argument("--fault", action="append", default=[], metavar="SPEC",
                   help=f"inject a fault into the replayed stream (repeatable; times in s from the first sample): {kinds}")
    p.add_argument("--fault-seed", type=int, default=0, metavar="N", help="seed of random faults (gps-multipath)")


def parse_faults(specs: Iterable[str] | None) -> list[Fault]:
    """Every spec of a repeatable ``--fault``; at most one clock step (two would be ambiguous to score)."""
    faults = [parse_fault(s) for s in specs or ()]
    steps = [f.spec for f in faults if f.kind == "clock-step"]
    if len(steps) > 1:
        raise FaultError(f"--fault: at most one clock-step per replay, got {', '.join(map(repr, steps))}")
    return faults
