"""The fused trajectory on disk: TUM lines that ``evo`` and ``vtolpose eval`` read."""

from __future__ import annotations

import contextlib
import logging
import math
from pathlib import Path
from typing import Iterator

from vtolpose.drivers.files.tum import TUM_HEADER, tum_line
from vtolpose.estimator import OutputPose

log = logging.getLogger(__name__)


class TrajectoryFile:
    """Fused poses appended as TUM lines (same format as ``vtolpose.drivers.files.tum.write_tum``), flushed each second."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.path.open("w", encoding="utf-8", newline="\n")
        self._file.write(TUM_HEADER + "\n")
        self.lines = 0
        self.skipped = 0
        self.error: str | None = None  # why some lines could not be written (a full disk), if so

    def write(self, pose: OutputPose) -> None:
        w, x, y, z = pose.q.tolist()
        values = (*pose.p.tolist(), x, y, z, w)
        if not all(map(math.isfinite, values)):
            self.skipped += 1
            return
        with self._noting_errors():
            self._file.write(tum_line(pose.t_ns, values) + "\n")
        self.lines += 1

    def flush(self) -> None:
        with self._noting_errors():
            self._file.flush()

    @contextlib.contextmanager
    def _noting_errors(self) -> Iterator[None]:
        """A write error (a full disk) is kept in ``error`` and raised to the caller, who counts it."""
        try:
            yield
        except OSError as exc:
            self.error = exc.strerror or str(exc)
            raise

    def close(self) -> None:
        """Write what is buffered and close. A write error here (a full disk) is logged and kept in
        ``error``, never raised: it must not turn the clean stop of a run into a failure."""
        if self._file.closed:
            return
        try:
            self._file.close()  # closed even when its last flush fails
        except OSError as exc:
            self.error = exc.strerror or str(exc)
        if self.error is not None:
            log.error("trajectory file %s is incomplete (%s): not all of the %d lines given to it were written",
                      self.path, self.error, self.lines)
