"""BLAS on one thread: the filter's matrices are small, and an idle BLAS pool's threads spin.

Measured on the 2-core target (book, imu,camera,gps): with OpenBLAS' default thread pool a
camera update took ~18 ms and SIFT ~80 ms per frame, because the pool's threads busy-wait
after each product and steal the core that feature extraction runs on; with one thread the
update takes ~3 ms and SIFT ~50 ms. ``OPENBLAS_NUM_THREADS=1`` in the environment does the
same, but only before numpy is imported; this sets it at run time through the library's own
``*_set_num_threads`` entry point (found among the loaded shared objects, Linux only).
OpenCV keeps its own pool: SIFT runs ~1.5x faster on two threads than on one.
"""

from __future__ import annotations

import ctypes
import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

_SETTERS = ("openblas_set_num_threads", "scipy_openblas_set_num_threads64_", "openblas_set_num_threads64_")


def _loaded_openblas() -> list[str]:
    maps = Path("/proc/self/maps")
    if not maps.is_file():
        return []
    paths = {line.split()[-1] for line in maps.read_text().splitlines() if "openblas" in line.lower() and "/" in line}
    return sorted(paths)


def limit_blas_threads(n: int = 1) -> int:
    """Set every loaded OpenBLAS to ``n`` threads; returns how many libraries were set."""
    np.dot(np.ones(2), np.ones(2))  # numpy's BLAS is loaded and initialised before we look for it
    done = 0
    for path in _loaded_openblas():
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in _SETTERS:
            setter = getattr(lib, name, None)
            if setter is not None:
                setter(ctypes.c_int(n))
                done += 1
                break
    if done == 0:
        log.debug("no OpenBLAS found to limit to %d thread(s); set OPENBLAS_NUM_THREADS instead", n)
    return done

