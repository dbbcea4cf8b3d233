"""The fused trajectory on disk: TUM lines that ``evo`` and ``vtolpose eval`` read."""

from __future__ import annotations

import math
from pathlib import Path

from vtolpose.drivers.files.tum import TUM_HEADER, tum_line
from vtolpose.estimator.fusion import OutputPose


class TrajectoryFile:
    """Fused poses appended as TUM lines (same format as ``vtolpose.drivers.files.tum.write_tum``), flushed each second."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.path.open("w", encoding="utf-8", newline="\n")
        self._file.write(TUM_HEADER + "\n")
        self.lines = 0
        self.skipped = 0

    def write(self, pose: OutputPose) -> None:
        w, x, y, z = pose.q.tolist()
        values = (*pose.p.tolist(), x, y, z, w)
        if not all(map(math.isfinite, values)):
            self.skipped += 1
            return
        self._file.write(tum_line(pose.t_ns, values) + "\n")
        self.lines += 1

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()
