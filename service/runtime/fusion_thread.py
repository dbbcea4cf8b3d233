"""A camera frame's update on a thread of its own, so that the IMU samples arriving meanwhile do not wait for it.

A frame's EKF-SLAM update takes milliseconds (8 ms p50 on the book's 60-landmark map, up to 40 ms on the
landfill's, docs/results.md); on the loop, every IMU sample that arrives during it would wait, and so would they
behind the once-a-second state check, which factorises the whole covariance (30 ms with 45 landmarks on a
2-core machine whose other core is busy). When the next advance of the delayed horizon does either
(``FusionCore.heavy_due``) the runtime hands that advance to :class:`FusionThread`, and until it is done
publishes each new sample's pose from a detached copy of the output predictor (``FusionCore.detached``: the
biases, flags and covariance of the moment it was cut loose). What arrives meanwhile (IMU samples, fixes,
features) is held in order and given to the fusion core once the thread is done, whose fused poses are
delivered then too. The loop never touches the fusion core or the estimator while the thread works on them:
one owner at a time, no lock on the filter.

The thread runs Python as well; while a runtime uses one, the interpreter's switch interval is shortened
(:data:`SWITCH_INTERVAL_S`) so that a loop woken by a sample takes the interpreter back within a fraction of a
millisecond instead of the default 5 ms.
"""

from __future__ import annotations

import asyncio
import sys
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

from vtolpose.estimator import DetachedPrediction, FusionCore

SWITCH_INTERVAL_S = 0.0002  # the interpreter's switch interval while a fusion thread may hold it
MAX_HELD = 4096  # what may wait for the thread (at 200 Hz, 20 s); more is dropped and counted

Done = Callable[[list[tuple[Callable[[Any], None], Any]], BaseException | None], None]


class FusionThread:
    """One advance of the delayed filter at a time on a thread, the detached prediction and the held inputs
    meanwhile. The loop calls everything here; only :meth:`hand_over`'s advance runs on the thread."""

    def __init__(self) -> None:
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fusion")
        self._future: asyncio.Future | None = None
        self.detached: DetachedPrediction | None = None
        self._held: list[Callable[[], Any]] = []
        self.handed = 0  # advances the thread has taken
        self.dropped = 0  # inputs refused because MAX_HELD were waiting
        self._switch_interval: float | None = None

    @property
    def busy(self) -> bool:
        return self._future is not None

    def open(self) -> None:
        """Shorten the interpreter's switch interval for the run (restored by :meth:`close`)."""
        self._switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(min(self._switch_interval, SWITCH_INTERVAL_S))

    def close(self) -> None:
        self._executor.shutdown(wait=True)
        if self._switch_interval is not None:
            sys.setswitchinterval(self._switch_interval)
            self._switch_interval = None

    def hand_over(self, fusion: FusionCore, done: Done) -> None:
        """``fusion.advance()`` on the thread. Then, on the loop: ``done(fused, error)`` with the fused poses the
        advance made (``(callback, pose or run)`` in order, the fusion core's own callbacks) and its exception."""
        self.detached = fusion.detached()
        fused: list[tuple[Callable[[Any], None], Any]] = []
        on_fused, on_fused_run = fusion.on_fused, fusion.on_fused_run
        if on_fused is not None:
            fusion.on_fused = lambda pose: fused.append((on_fused, pose))
        if on_fused_run is not None:
            fusion.on_fused_run = lambda run: fused.append((on_fused_run, run))
        future = asyncio.get_running_loop().run_in_executor(self._executor, fusion.advance)
        self._future = future
        self.handed += 1

        def finished(f: asyncio.Future) -> None:
            fusion.on_fused, fusion.on_fused_run = on_fused, on_fused_run
            self._future, self.detached = None, None
            done(fused, None if f.cancelled() else f.exception())

        future.add_done_callback(finished)

    def hold(self, action: Callable[[], Any]) -> bool:
        """Keep ``action`` (a sample or measurement for the fusion core) until the thread is done; False: refused."""
        if len(self._held) >= MAX_HELD:
            self.dropped += 1
            return False
        self._held.append(action)
        return True

    def take_held(self) -> list[Callable[[], Any]]:
        held, self._held = self._held, []
        return held

    async def idle(self) -> None:
        """Return once no advance is on the thread (and its ``done`` has run)."""
        while self._future is not None:
            await asyncio.wait({self._future})
            await asyncio.sleep(0)

    def report(self) -> dict[str, int]:
        return {"advances": self.handed, "held_dropped": self.dropped}
