"""The estimator's compiled kernels (numba) for a command: loaded from the cache, or compiled once.

Compiling them all takes about half a minute on a small computer, once per machine and installed version;
loading them from the cache a fraction of a second. A benchmark, ``vtolpose warmup`` and library callers wait
for the compiler and say once that it runs. A command a user waits on (``vtolpose replay``, ``demo``, ``run``:
the program, see :func:`compile_in_background`) does not: with a cold cache it runs the kernels as plain
Python, the same operations in the same order and so the same numbers (tests hold the kernels to their
interpreted runs bit for bit), and a low-priority process fills the cache: started once the command has run
``COMPILE_AFTER_S`` interpreted, or as it ends, whichever comes first. A short command so never shares the
computer with its compiler (on two cores that share one physical core, a compiler at any priority slows the
run by a third) and leaves it behind for the next; a long run switches to the compiled kernels as soon as they
are there. The command hands the compiler the compile lock it took, so whoever waits for the lock waits for
that compiler. Callers load the kernels before they start a clock, so no speed figure counts compiling or
loading them.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

log = logging.getLogger(__name__)

COMPILE_COMMAND = (sys.executable, "-m", "vtolpose", "-q", "warmup", "--nice")
COMPILE_AFTER_S = 10.0  # interpreted this long, a run starts the background compiler; a shorter one as it ends
LOCK_FD_ENV = "VTOLPOSE_COMPILE_LOCK_FD"  # the compile lock's descriptor, held for the compiler by who started it


@dataclass(frozen=True)
class KernelLoad:
    """How this process has its kernels: ``compiled`` (``compile_s`` spent compiling them, None when they
    came from the cache in ``load_s``) or ``interpreted`` while the cache is filled in the background."""

    mode: str
    load_s: float = 0.0
    compile_s: float | None = None

    def describe(self) -> str:
        if self.mode == "interpreted":
            return "kernels interpreted while they compile in the background (once): the next run is faster"
        if self.compile_s is not None:
            return f"kernels compiled in {self.compile_s:.1f} s (once; not in the figures)"
        return f"kernels loaded from the cache in {self.load_s:.2f} s (not in the figures)"


class _Process:
    """This process's kernel state: whether it may go on interpreted, whether it is, and who watches the
    background compiler."""

    def __init__(self) -> None:
        self.background = False
        self.interpreted = False
        self.announced = False
        self.watcher: threading.Thread | None = None
        self.lock = threading.RLock()
        self.start_now = threading.Event()  # the compiler is wanted at once (the run ends, or someone waits)
        self.launched = False
        self.compiler: subprocess.Popen | None = None


_process = _Process()


def compile_in_background(enabled: bool = True) -> None:
    """Let a cold cache be filled in the background while this process runs the kernels interpreted (the
    ``vtolpose`` program sets it; a library caller, e.g. a test, waits for the compiler instead)."""
    _process.background = enabled


def load_compiled_kernels(backward_pass: bool = False, runs: bool = True, wait: bool | None = None) -> KernelLoad:
    """The estimator's kernels ready before the first sample is handled: loaded from the cache, else compiled
    (``wait``, by default unless :func:`compile_in_background`), else interpreted while a background process
    compiles them. ``backward_pass``: also the offline smoother's. ``runs``: also those of runs of samples,
    which a live service, sample by sample, never calls (~5 MB less); a kernel left out here still loads on its
    first call."""
    wait = not _process.background if wait is None else wait
    with _process.lock:
        if _process.interpreted and not wait:
            return KernelLoad("interpreted")
    if _process.interpreted:
        _wait_for_background_compiler()
    with _process.lock:
        if not wait:
            started = time.perf_counter()
            if _load_from_cache(backward_pass, runs):
                return KernelLoad("compiled", time.perf_counter() - started)
            _go_interpreted()
            return KernelLoad("interpreted")
        return _load_or_compile(backward_pass, runs)


def warm_up(backward_pass: bool = True, runs: bool = True, view: Callable[[Callable], Callable] = lambda f: f) -> None:
    """Call every kernel on the argument types the estimator passes: each is loaded, or compiled and cached.
    ``view``: how each module's warm-up sees its kernels (``kernel_swap.compiled_view`` while they are swapped out)."""
    from vtolpose.estimator import gps_kernel, propagation_kernel, rts_kernel, sample_kernel, update_kernel

    view(propagation_kernel.warm_up)(runs)
    view(update_kernel.warm_up)()
    view(gps_kernel.warm_up)()
    view(sample_kernel.warm_up)(runs)
    view(rts_kernel.warm_up)(backward_pass)


class _ColdCache(Exception):
    """Raised into numba when it is about to compile: the cache lacks a kernel."""


class _CompileWatch:
    """A numba ``numba:compile`` listener: notes the first compile, says it once, or stops it (``refuse``)."""

    def __init__(self, refuse: bool) -> None:
        self.refuse = refuse
        self.first: float | None = None

    def notify(self, event) -> None:
        if not event.is_start:
            return
        if self.refuse:
            raise _ColdCache
        if self.first is None:
            self.first = time.perf_counter()
            if not _process.announced:
                _process.announced = True
                log.info("compiling the estimator's kernels, once (about half a minute), into %s", cache_place())


@contextlib.contextmanager
def _watching(watch: _CompileWatch) -> Iterator[None]:
    from numba.core import event

    listener = type("Listener", (event.Listener,), {"on_start": lambda self, e: watch.notify(e),
                                                    "on_end": lambda self, e: None})()
    with event.install_listener("numba:compile", listener):
        yield


def _load_or_compile(backward_pass: bool, runs: bool) -> KernelLoad:
    started = time.perf_counter()
    watch = _CompileWatch(refuse=False)
    with _watching(watch):
        warm_up(backward_pass, runs)
    spent = time.perf_counter() - started
    if watch.first is None:
        return KernelLoad("compiled", spent)
    log.info("compiled the estimator's kernels, once (%.1f s)", spent)
    return KernelLoad("compiled", spent, spent)


def _load_from_cache(backward_pass: bool, runs: bool) -> bool:
    """Load the kernels from the cache; False, having compiled nothing, when one is not there."""
    view = (lambda f: f)
    if _process.interpreted:
        from vtolpose.service.runtime.kernel_swap import compiled_view as view
    try:
        with _watching(_CompileWatch(refuse=True)):
            warm_up(backward_pass, runs, view)
    except _ColdCache:
        return False
    return True


def cache_place() -> str:
    from vtolpose.estimator import kernel_cache

    return kernel_cache.kernel_cache_place()


def compile_lock_path() -> Path:
    """The file a compiler holds locked while it fills the cache (one compiler at a time)."""
    from vtolpose.estimator import kernel_cache

    folder = Path(os.environ.get("NUMBA_CACHE_DIR") or kernel_cache.ESTIMATOR_DIR / "__pycache__")
    return folder / ".vtolpose-compiling.lock"


def _inherited_lock() -> int | None:
    """The compile lock's descriptor the command that started this compiler handed over, if any (and open)."""
    given = os.environ.pop(LOCK_FD_ENV, None)  # not passed on to what this process starts
    if not given:
        return None
    try:
        fd = int(given)
        os.fstat(fd)
    except (ValueError, OSError):
        log.warning("%s=%r is not an open descriptor: taking the compile lock afresh", LOCK_FD_ENV, given)
        return None
    return fd


def _take_lock(block: bool) -> tuple[bool, int | None]:
    """The compile lock on a descriptor of this process's own: (held, descriptor; closing it releases the lock).
    (True, None) where there are no advisory locks: compilers may overlap there, which only costs time."""
    path = compile_lock_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:
        return True, None
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX if block else fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return False, None
    return True, fd


@contextlib.contextmanager
def compile_lock(block: bool = True) -> Iterator[bool]:
    """Hold the compiler's lock (waiting for another compiler when ``block``); yields whether it is held. A
    compiler started by :func:`_start_compiler` holds it already, through the descriptor it was handed."""
    inherited = _inherited_lock()
    held, fd = (True, inherited) if inherited is not None else _take_lock(block)
    try:
        yield held
    finally:
        if fd is not None:
            os.close(fd)  # its last descriptor: the lock is released


def _go_interpreted() -> None:
    """Run the kernels interpreted and leave a compiler for later: started by a watcher after COMPILE_AFTER_S, or
    when the process ends; the watcher then switches to what it cached."""
    from vtolpose.service.runtime import kernel_swap

    kernel_swap.to_interpreted()
    _process.interpreted = True
    log.info("compiling the estimator's kernels, once, in the background into %s (from %g s into this run, or as it "
             "ends); until they are ready this process runs them interpreted (the same results, slower)",
             cache_place(), COMPILE_AFTER_S)
    _process.announced = True
    atexit.register(_launch_compiler)
    _process.watcher = threading.Thread(target=_switch_when_compiled, name="kernel-compiler-watch", daemon=True)
    _process.watcher.start()


def _launch_compiler() -> subprocess.Popen | None:
    """Start the background compiler, once per process: None when another compiler holds the lock (or none
    could start)."""
    with _process.lock:
        if not _process.launched and _process.interpreted:
            _process.launched = True
            _process.compiler = _start_compiler()
        return _process.compiler


def _start_compiler() -> subprocess.Popen | None:
    """``vtolpose warmup --nice`` in its own session, the compile lock taken here and handed to it: it outlives a
    short command and fills the cache for the next, and whoever waits for the lock waits for it. None: another
    compiler holds the lock."""
    try:
        held, fd = _take_lock(block=False)
    except OSError as exc:
        log.warning("could not take the compile lock (%s): the kernels stay interpreted in this run", exc)
        return None
    if not held:
        return None
    try:
        env = dict(os.environ, **({LOCK_FD_ENV: str(fd)} if fd is not None else {}))
        return subprocess.Popen(COMPILE_COMMAND, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, start_new_session=True, env=env,
                                pass_fds=(fd,) if fd is not None else ())
    except OSError as exc:
        log.warning("could not start the background compiler (%s): the kernels stay interpreted in this run", exc)
        return None
    finally:
        if fd is not None:
            os.close(fd)  # the compiler's copy keeps the lock


def _switch_when_compiled() -> None:
    """After COMPILE_AFTER_S interpreted (or at once if asked), start the compiler; wait for it (or for another
    process's, through the lock), then load what it cached and switch to it."""
    _process.start_now.wait(COMPILE_AFTER_S)
    compiler = _launch_compiler()
    if compiler is not None:
        compiler.wait()
    else:
        with compile_lock(block=True) as held:  # taking the lock is the wait: it is free once the other compiler ends
            log.debug("the other process's compiler has ended (lock %s)", "taken" if held else "not available")
    from vtolpose.service.runtime import kernel_swap

    with _process.lock:
        loaded = _load_from_cache(True, True)
        if loaded:
            kernel_swap.to_compiled()
            _process.interpreted = False
    if loaded:
        log.info("the estimator's compiled kernels are ready: switched to them")
    else:
        log.warning("the background compiler left the kernel cache incomplete: this run stays interpreted")


def _wait_for_background_compiler() -> None:
    _process.start_now.set()
    watcher = _process.watcher
    if watcher is not None:
        watcher.join()
    with _process.lock:
        if _process.interpreted:  # the compiler failed: compile here
            from vtolpose.service.runtime import kernel_swap

            kernel_swap.to_compiled()
            _process.interpreted = False
