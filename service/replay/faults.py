"""Fault injection for replays: sensor loss, outliers, frozen frames, clock steps, NaN bursts.

A fault is a deterministic transformation of the sample stream between the dataset and the
runtime, so the estimator meets it exactly as it would meet a failing device: nothing inside
the estimator knows a fault is being played. Times in a spec are seconds of data from the
first sample of the replay. ``--fault`` specs:

    gps-off:START:DURATION                 no GPS fixes in the window
    camera-off:START:DURATION              no camera frames in the window
    imu-gap:START:DURATION                 no IMU samples in the window
    gps-jump:START:DN,DE,DD[:DURATION]     fixes displaced by (DN, DE, DD) m for DURATION s (default 1)
    gps-multipath:START:DURATION:SIGMA:RATE  a fraction RATE of the fixes displaced by N(0, SIGMA²) per axis
    camera-freeze:START:DURATION           every frame in the window repeats the last image before it
    gps-sigma:START:DURATION:SIGMA         fixes claim a 1-sigma of SIGMA m (e.g. 1e-300: a receiver that lies)
    clock-step:T:STEP                      every sample stamp from T on moves by STEP s (e.g. +2.0)
    nan:SENSOR:START:DURATION              SENSOR (imu | gps) values are NaN in the window

Random choices (multipath) come from a generator seeded by ``seed`` and the fault's position
in the list, drawn in stream order: the same specs and seed give the same stream.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, AsyncIterator, Iterable, Sequence

import numpy as np

from vtolpose.estimator import CameraFrame, GpsFix, ImuBatch, ImuSample

__all__ = ["FAULT_KINDS", "Fault", "FaultError", "FaultInjector", "FaultyStream", "add_fault_options", "inject",
           "injector_from", "parse_fault", "parse_faults"]

Sample = ImuSample | GpsFix | CameraFrame

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


def injector_from(args: argparse.Namespace) -> FaultInjector | None:
    """The injector for ``--fault``/``--fault-seed`` (None without faults); FaultError names a bad spec."""
    faults = parse_faults(getattr(args, "fault", None))
    return FaultInjector(faults, getattr(args, "fault_seed", 0)) if faults else None


def parse_faults(specs: Iterable[str] | None) -> list[Fault]:
    """Every spec of a repeatable ``--fault``; at most one clock step (two would be ambiguous to score)."""
    faults = [parse_fault(s) for s in specs or ()]
    steps = [f.spec for f in faults if f.kind == "clock-step"]
    if len(steps) > 1:
        raise FaultError(f"--fault: at most one clock-step per replay, got {', '.join(map(repr, steps))}")
    return faults


def _sensor_of(sample: Sample) -> str:
    return "imu" if isinstance(sample, ImuSample) else "gps" if isinstance(sample, GpsFix) else "camera"


@dataclass
class FaultInjector:
    """Applies faults to samples one at a time, in stream order; counts what each fault did."""

    faults: Sequence[Fault]
    seed: int = 0
    t0_ns: int | None = None  # data time zero; None: the first sample's stamp
    affected: list[int] = field(init=False)

    def __post_init__(self) -> None:
        self.faults = list(self.faults)
        self.affected = [0] * len(self.faults)
        self._rngs = [np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(k,)))
                      for k in range(len(self.faults))]
        self._frozen: dict[int, np.ndarray | None] = {}  # camera-freeze index -> the image it repeats
        self._last_image: np.ndarray | None = None
        self._nan3 = np.full(3, np.nan)

    def apply(self, sample: Sample) -> Sample | None:
        """The sample as the faulty system delivers it, or None if it is lost."""
        if self.t0_ns is None:
            self.t0_ns = sample.t_ns
        t_s = (sample.t_ns - self.t0_ns) * 1e-9
        sensor = _sensor_of(sample)
        original = sample
        for k, fault in enumerate(self.faults):
            if fault.kind == "clock-step":
                if t_s >= fault.start_s:
                    sample = dataclasses.replace(sample, t_ns=sample.t_ns + int(round(fault.step_s * 1e9)))
                    self.affected[k] += 1
                continue
            if fault.sensor != sensor or not fault.covers(t_s):
                continue
            changed = self._apply_one(k, fault, sample)
            if changed is not sample:
                self.affected[k] += 1
            if changed is None:
                return None
            sample = changed
        if sensor == "camera" and sample.image is original.image:
            self._last_image = original.image
        return sample

    def _apply_one(self, k: int, fault: Fault, sample: Sample) -> Sample | None:
        kind = fault.kind
        if kind in ("gps-off", "camera-off", "imu-gap"):
            return None
        if kind == "gps-jump":
            return dataclasses.replace(sample, p_ned=np.asarray(sample.p_ned, float) + np.array(fault.offset_m))
        if kind == "gps-multipath":
            rng = self._rngs[k]
            hit, noise = rng.random() < fault.rate, rng.normal(0.0, fault.sigma_m, 3)  # both drawn: fixed stream
            return dataclasses.replace(sample, p_ned=np.asarray(sample.p_ned, float) + noise) if hit else sample
        if kind == "gps-sigma":
            return dataclasses.replace(sample, sigma_h=fault.sigma_m, sigma_v=fault.sigma_m)
        if kind == "camera-freeze":
            if k not in self._frozen:
                self._frozen[k] = self._last_image if self._last_image is not None else sample.image
            return dataclasses.replace(sample, image=self._frozen[k])
        # nan
        if isinstance(sample, ImuSample):
            return dataclasses.replace(sample, gyro=self._nan3, accel=self._nan3)
        return dataclasses.replace(sample, p_ned=self._nan3)

    def source_time_ns(self, t_ns: np.ndarray) -> np.ndarray:
        """Stamps as the faulty stream gave them back to data time (clock steps undone), for scoring.

        After a step at T every sample stamped at or after T (in data time) carries the step;
        the estimator rejects samples that go back in time, so whatever it stamped at or after T
        came from after the step.
        """
        t_ns = np.asarray(t_ns, dtype=np.int64).copy()
        if self.t0_ns is None:
            return t_ns
        for fault in self.faults:
            if fault.kind == "clock-step":
                t_step = self.t0_ns + int(round(fault.start_s * 1e9))
                t_ns[t_ns >= t_step] -= int(round(fault.step_s * 1e9))
        return t_ns

    def report(self) -> list[dict[str, Any]]:
        """Each fault as given, with the number of samples it dropped or changed."""
        return [{**f.describe(), "samples_affected": n} for f, n in zip(self.faults, self.affected)]


class FaultyStream:
    """``source`` with ``injector``'s faults applied, as an async iterator the runtime reads like any source.

    ``last_arrival_ns`` is the source's, so latency figures still start at the hand-over.
    """

    def __init__(self, source: AsyncIterator[Sample], injector: FaultInjector) -> None:
        self.source = source
        self.injector = injector

    @property
    def last_arrival_ns(self) -> int | None:
        return getattr(self.source, "last_arrival_ns", None)

    async def __aiter__(self) -> AsyncIterator[Sample]:
        async for item in self.source:
            # Faults act on single samples: a batch of IMU samples (a full-speed replay) is taken apart.
            for sample in item.samples() if isinstance(item, ImuBatch) else (item,):
                out = self.injector.apply(sample)
                if out is not None:
                    yield out


def inject(source: AsyncIterator[Sample], injector: FaultInjector) -> FaultyStream:
    return FaultyStream(source, injector)
