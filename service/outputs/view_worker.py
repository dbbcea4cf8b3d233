"""One background thread that encodes and writes for a view or a recording (Foxglove, MCAP).

The runtime's loop hands over immutable poses, samples and frame results through a bounded
queue and goes on; JPEG/PNG, JSON, protobuf, CDR and file writes happen here.
"""

from __future__ import annotations

import logging
import queue
import threading
from typing import Any, Callable

from vtolpose.service.runtime.loop import background_thread_priority

log = logging.getLogger(__name__)


class ViewWorker:
    """Encoding and writing for a view or a recording on one background thread, fed by a bounded queue.

    The runtime's loop only hands over immutable poses, samples and frame results, so the pose
    path never waits for JPEG/PNG, JSON, protobuf or the file. The thread runs niced like the camera
    workers. A full queue drops the item and counts it; a failing item is counted and logged once.
    """

    def __init__(self, name: str, capacity: int = 4096) -> None:
        self.name = name
        self.queue: queue.Queue = queue.Queue(capacity)
        self.stats = {"queued": 0, "dropped_full": 0, "failures": 0, "last_failure": None}
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def submit(self, work: Callable[..., None], *args: Any) -> None:
        try:
            self.queue.put_nowait((work, args))
            self.stats["queued"] += 1
        except queue.Full:
            self.stats["dropped_full"] += 1

    def _run(self) -> None:
        background_thread_priority()
        while True:
            work, args = self.queue.get()
            if work is None:
                return
            try:
                work(*args)
            except Exception as exc:  # one bad item must not end the view or the recording
                if not self.stats["failures"]:
                    log.exception("%s: %s failed", self.name, getattr(work, "__name__", work))
                self.stats["failures"] += 1
                self.stats["last_failure"] = repr(exc)

    def stop(self, timeout_s: float = 30.0) -> None:
        """Finish what is queued, then end the thread."""
        if self._thread is None:
            return
        self.queue.put((None, ()), timeout=timeout_s)
        self._thread.join(timeout_s)
        self._thread = None
