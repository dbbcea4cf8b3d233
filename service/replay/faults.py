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
from dataclasses import dataclass, field
from typing import Any, AsyncIterator, Sequence

import numpy as np

from vtolpose.estimator import CameraFrame, GpsFix, ImuBatch, ImuSample
from vtolpose.service.replay.fault_specs import (
    FAULT_KINDS, MAX_CLOCK_STEP_S, Fault, FaultError, add_fault_options, parse_fault, parse_faults,
)

__all__ = ["FAULT_KINDS", "MAX_CLOCK_STEP_S", "Fault", "FaultError", "FaultInjector", "FaultyStream", "add_fault_options", "inject",
           "injector_from", "parse_fault", "parse_faults"]

Sample = ImuSample | GpsFix | CameraFrame


def injector_from(args: argparse.Namespace) -> FaultInjector | None:
    """The injector for ``--fault``/``--fault-seed`` (None without faults); FaultError names a bad spec."""
    faults = parse_faults(getattr(args, "fault", None))
    return FaultInjector(faults, getattr(args, "fault_seed", 0)) if faults else None


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
