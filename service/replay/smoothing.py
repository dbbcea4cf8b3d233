"""``replay --smooth``: the forward pass's steps streamed to disk, the backward pass, the outputs.

During the replay the runtime records one step per filter propagation
(``vtolpose.estimator.smoothing``); :class:`StepFiles` writes them a chunk at a time into a
temporary folder, so memory stays at one chunk whatever the flight's length (an hour at
100 Hz is ~360 000 steps, ~2 GB on disk). The runtime's fixed-lag smoother runs as it would in
the daemon and its poses are kept for the report. After the replay, :meth:`ReplaySmoothing.backward`
reads the chunks newest first and runs the RTS pass over them, each smoothed chunk going back to
disk as it comes; then reads those oldest first to write the smoothed trajectory (TUM) and, if
asked, its pose covariance per line, in time order. What stays in memory is one chunk, the
smoothed times, positions, velocities and attitudes (88 bytes a pose, for scoring) and the
covariances sampled for the NEES check.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from vtolpose.drivers.files.csvio import seconds_text
from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.files.tum import tum_line
from vtolpose.estimator import BackwardPass, ChunkBuilder, SmoothedChunk, SmoothedPose, Step, StepChunk
from vtolpose.config.sections import SmoothingSection
from vtolpose.service.replay.session import CovarianceSamples, ReplayResult, Trajectory, replay
from vtolpose.service.runtime.step_taps import SmoothingPlan
from vtolpose.service.runtime.wiring import config_sections
from vtolpose.service.runtime.kernels import load_compiled_kernels

COV_HEADER = "# t [s], upper triangle of the 6x6 covariance of [dp (m), dtheta (rad, world frame)], row by row\n"
_UPPER = np.triu_indices(6)


@dataclass(frozen=True, slots=True)
class SmoothingOptions:
    fixed_lag_s: float = 2.0
    steps_per_sample: int = 4
    max_window_s: float = 10.0
    chunk_steps: int = 2048
    temp_dir: str | None = None

    @classmethod
    def from_section(cls, smoothing: SmoothingSection) -> "SmoothingOptions":
        return cls(smoothing.fixed_lag_s, smoothing.steps_per_sample, smoothing.max_window_s, smoothing.chunk_steps,
                   smoothing.temp_dir)


def _save(folder: Path, arrays: dict[str, np.ndarray]) -> int:
    folder.mkdir()
    for name, array in arrays.items():
        np.save(folder / f"{name}.npy", array)
    return sum(a.nbytes for a in arrays.values())


def _load(folder: Path, names: tuple[str, ...]) -> list[np.ndarray]:
    return [np.load(folder / f"{name}.npy") for name in names]


_SMOOTHED_FIELDS = ("t_ns", "x", "pose_cov", "vel_var", "segment", "heading_known")


class StepFiles:
    """Steps written a chunk per ``.npy`` set in a temporary folder, read back newest chunk first."""

    def __init__(self, chunk_steps: int, folder: str | None = None) -> None:
        try:
            self._dir = tempfile.TemporaryDirectory(prefix="vtolpose-smooth-", dir=folder)
        except OSError as exc:
            raise OSError(f"key 'smoothing.temp_dir': cannot make a folder for the forward record in "
                          f"{folder or tempfile.gettempdir()}: {exc}") from None
        self.root = Path(self._dir.name)
        self._builder = ChunkBuilder(self._write, chunk_steps)
        self.chunks = 0
        self.bytes = 0
        self.error: OSError | None = None  # the first write that failed (a full disk): recording stopped there

    @property
    def steps(self) -> int:
        return self._builder.steps

    def add(self, step: Step) -> None:
        if self.error is None:
            self._builder.add(step)

    def _write(self, chunk: StepChunk) -> None:
        try:
            self.bytes += _save(self.root / f"{self.chunks:06d}", chunk.arrays())
        except OSError as exc:  # the filter goes on; the smoothing cannot, and says why at the end
            self.error = exc
            return
        self.chunks += 1

    def newest_first(self) -> Iterator[StepChunk]:
        if self.error is None:
            self._builder.flush()
        if self.error is not None:
            raise OSError(f"the forward record for smoothing could not be written to {self.root} "
                          f"({self.error}); set smoothing.temp_dir to a folder with room (~5.7 kB per filter step)")
        for k in range(self.chunks - 1, -1, -1):
            yield StepChunk(*_load(self.root / f"{k:06d}", StepChunk.FIELDS))

    def close(self) -> None:
        self._dir.cleanup()


class _CovarianceSampler:
    """Pose covariances at most every ``period_ns`` (what the report's NEES check reads), from ``start_ns``."""

    def __init__(self, period_ns: int) -> None:
        self.period_ns = period_ns
        self._next = None
        self.rows: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []

    def add(self, t_ns: np.ndarray, p: np.ndarray, q: np.ndarray, cov: np.ndarray, start_ns: int) -> None:
        for k in range(len(t_ns)):
            t = int(t_ns[k])
            if t < start_ns or (self._next is not None and t < self._next):
                continue
            self.rows.append((t, p[k].copy(), q[k].copy(), cov[k].copy()))
            self._next = t + self.period_ns

    def samples(self) -> CovarianceSamples:
        return CovarianceSamples.from_rows(self.rows)


@dataclass
class SmoothingResult:
    """Smoothed and fixed-lag trajectories of a replay, with their covariance samples and costs."""

    smoothed: Trajectory
    smoothed_cov: CovarianceSamples
    fixed_lag: Trajectory
    fixed_lag_cov: CovarianceSamples
    lag_s: float
    steps: int
    segments: int
    backward_s: float
    disk_bytes: int
    fixed_lag_dropped: int = 0
    notes: list[str] = field(default_factory=list)


class ReplaySmoothing:
    """Give a replay its :meth:`plan` and :meth:`attach` to its runtime, run it, then :meth:`backward`."""

    def __init__(self, options: SmoothingOptions, cov_period_ns: int) -> None:
        self.options = options
        self.files = StepFiles(options.chunk_steps, options.temp_dir)
        self.cov_period_ns = cov_period_ns
        self._fixed: list[tuple[np.ndarray, np.ndarray]] = []  # (times, p v q) per batch handed out
        self._fixed_cov: list[tuple[int, np.ndarray]] = []
        self._next_fixed_cov: int | None = None
        self._runtime: Any = None

    def plan(self) -> SmoothingPlan:
        """The filter's steps to disk, and the fixed-lag smoother's."""
        o = self.options
        return SmoothingPlan(o.fixed_lag_s, o.steps_per_sample, o.max_window_s, step_sink=self.files.add)

    def attach(self, runtime: Any) -> None:
        """Keep the runtime's fixed-lag poses."""
        runtime.smoothed_hook = self._on_fixed_lag
        self._runtime = runtime

    def _on_fixed_lag(self, poses: list[SmoothedPose]) -> None:
        self._fixed.append((np.array([pose.t_ns for pose in poses], dtype=np.int64),
                            np.array([pose.x[0:10] for pose in poses])))
        for pose in poses:
            if self._next_fixed_cov is None or pose.t_ns >= self._next_fixed_cov:
                self._fixed_cov.append((pose.t_ns, pose.pose_cov))
                self._next_fixed_cov = pose.t_ns + self.cov_period_ns

    def backward(self, nees_from_ns: int, out: str | Path | None = None, cov_out: str | Path | None = None) -> SmoothingResult:
        """The RTS pass over the recorded steps; TUM trajectory to ``out`` and covariances to ``cov_out`` if given.

        ``nees_from_ns``: covariance samples start here (the filtered ones start once the position is known).
        """
        t0 = time.perf_counter()
        backward = BackwardPass()
        smoothed_dir = self.files.root / "smoothed"
        smoothed_dir.mkdir()
        parts, segments = 0, set()
        for chunk in self.files.newest_first():  # newest first: each smoothed chunk to disk as it comes
            part = backward.chunk(chunk)
            _save(smoothed_dir / f"{parts:06d}", {name: getattr(part, name) for name in _SMOOTHED_FIELDS})
            segments.update(np.unique(part.segment).tolist())
            parts += 1
        sampler = _CovarianceSampler(self.cov_period_ns)
        times, nominal = [], []
        with _TrajectoryFiles(out, cov_out) as files:
            for k in range(parts - 1, -1, -1):  # then read back oldest first: the files in time order
                part = SmoothedChunk(*_load(smoothed_dir / f"{k:06d}", _SMOOTHED_FIELDS))
                files.write(part)
                sampler.add(part.t_ns, part.p, part.q, part.pose_cov, nees_from_ns)
                times.append(part.t_ns)
                nominal.append(part.x[:, 0:10])  # what scoring reads: p, v, q
        t = np.concatenate(times) if times else np.zeros(0, np.int64)
        x = np.concatenate(nominal) if nominal else np.zeros((0, 10))
        backward_s = time.perf_counter() - t0
        smoother = self._runtime.smoother if self._runtime is not None else None
        result = SmoothingResult(
            Trajectory(t, x[:, 0:3], x[:, 3:6], x[:, 6:10]), sampler.samples(), *self._fixed_lag(nees_from_ns),
            lag_s=self.options.fixed_lag_s, steps=self.files.steps, segments=len(segments), backward_s=backward_s,
            disk_bytes=self.files.bytes, fixed_lag_dropped=smoother.dropped if smoother is not None else 0,
        )
        self.files.close()
        return result

    def _fixed_lag(self, nees_from_ns: int) -> tuple[Trajectory, CovarianceSamples]:
        if not self._fixed:
            empty = Trajectory(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 4)))
            return empty, _CovarianceSampler(self.cov_period_ns).samples()
        t = np.concatenate([r[0] for r in self._fixed])
        x = np.concatenate([r[1] for r in self._fixed])
        traj = Trajectory(t, x[:, 0:3], x[:, 3:6], x[:, 6:10])
        rows = [(tc, c) for tc, c in self._fixed_cov if tc >= nees_from_ns]
        if not rows:
            return traj, _CovarianceSampler(self.cov_period_ns).samples()
        tc = np.array([r[0] for r in rows], dtype=np.int64)
        k = np.searchsorted(t, tc)
        return traj, CovarianceSamples(tc, x[k, 0:3], x[k, 6:10], np.array([r[1] for r in rows]))

    def close(self) -> None:
        self.files.close()


class _TrajectoryFiles:
    """The smoothed trajectory (TUM, NED/FRD) and one covariance line per pose, written chunk by chunk."""

    def __init__(self, out: str | Path | None, cov_out: str | Path | None) -> None:
        self.traj = open(out, "w", encoding="utf-8") if out is not None else None
        self.cov = open(cov_out, "w", encoding="utf-8") if cov_out is not None else None
        if self.cov is not None:
            self.cov.write(COV_HEADER)

    def __enter__(self) -> "_TrajectoryFiles":
        return self

    def __exit__(self, *exc: object) -> None:
        for f in (self.traj, self.cov):
            if f is not None:
                f.close()

    def write(self, part: SmoothedChunk) -> None:
        for k in range(len(part)):
            t = int(part.t_ns[k])
            if self.traj is not None:
                w, x, y, z = part.q[k].tolist()
                self.traj.write(tum_line(t, [*part.p[k].tolist(), x, y, z, w]) + "\n")
            if self.cov is not None:
                self.cov.write(seconds_text(t) + "," + ",".join(f"{v:.6e}" for v in part.pose_cov[k][_UPPER]) + "\n")


def replay_smoothed(dataset: Dataset, cfg: dict[str, Any], out: str | Path | None = None,
                    cov_out: str | Path | None = None, **replay_args: Any) -> ReplayResult:
    """:func:`~vtolpose.service.replay.session.replay` with the backward pass after it: the result's
    ``smoothing`` holds the smoothed and fixed-lag trajectories; ``out``/``cov_out`` get the smoothed
    trajectory (TUM) and its covariances."""
    kernels = load_compiled_kernels(backward_pass=True)  # the backward pass's too: not in its time either
    sections = config_sections(cfg)
    smoothing = ReplaySmoothing(SmoothingOptions.from_section(sections.smoothing), int(1e9 / sections.replay.nees_rate_hz))
    try:
        result = replay(dataset, cfg, prepare=smoothing.attach, smoothing=smoothing.plan(), **replay_args)
        result.kernels = kernels
        cov = result.covariances
        start = int(cov.t_ns[0]) if len(cov.t_ns) else int(result.trajectory.t_ns[0]) if len(result.trajectory.t_ns) else 0
        result.smoothing = smoothing.backward(start, out, cov_out)
    finally:
        smoothing.close()
    return result
