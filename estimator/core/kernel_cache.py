"""Where numba keeps the estimator's compiled kernels, chosen before any kernel module imports numba.

numba caches a kernel beside its source (``__pycache__``) when that folder is writable: a clone, an
editable install. A read-only site-packages would leave it only numba's own user-wide fallback, which no
message of ours could name; so there the kernels go to the user's cache, ``$XDG_CACHE_HOME/vtolpose/numba``
(``~/.cache/vtolpose/numba``), set as ``NUMBA_CACHE_DIR`` so that a background compiler this process
starts shares it. A ``NUMBA_CACHE_DIR`` already set (the Docker image's) is left as it is.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

ESTIMATOR_DIR = Path(__file__).resolve().parents[1]
KERNEL_FOLDERS = ("core", "inertial", "gnss", "smoothing")  # where the numba kernels' sources are


def user_cache_dir() -> Path:
    """The per-user cache of compiled kernels (XDG base directories)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "vtolpose" / "numba"


def sources_writable(root: Path = ESTIMATOR_DIR) -> bool:
    """Whether numba may write its cache beside every kernel's source (each folder's ``__pycache__``)."""
    for folder in (root / name for name in KERNEL_FOLDERS):
        pycache = folder / "__pycache__"
        target = pycache if pycache.is_dir() else folder
        if not os.access(target, os.W_OK):
            return False
    return True


def choose_kernel_cache() -> Path | None:
    """The folder the kernels are cached in, ``NUMBA_CACHE_DIR`` set to it when it must be; None: beside
    their sources. Also applied to a numba imported already (its setting is read when a kernel is defined)."""
    given = os.environ.get("NUMBA_CACHE_DIR")
    if given:
        return Path(given)
    if sources_writable():
        return None
    folder = user_cache_dir()
    os.environ["NUMBA_CACHE_DIR"] = str(folder)
    numba_config = sys.modules.get("numba.core.config")
    if numba_config is not None:
        numba_config.CACHE_DIR = str(folder)
    return folder


def kernel_cache_place() -> str:
    """Where the kernels are cached, in words for a message."""
    given = os.environ.get("NUMBA_CACHE_DIR")
    return given if given else f"{ESTIMATOR_DIR}/*/__pycache__"
