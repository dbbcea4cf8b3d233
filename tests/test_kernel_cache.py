"""The kernels' cache where a user can write, and a cold cache met without waiting: the kernels interpreted,
the same numbers, while a background ``vtolpose warmup`` compiles them (service/runtime/kernels.py)."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vtolpose.estimator.core import kernel_cache


def test_a_read_only_install_caches_its_kernels_in_the_users_cache(monkeypatch, tmp_path):
    import numba.core.config

    monkeypatch.setattr(numba.core.config, "CACHE_DIR", numba.core.config.CACHE_DIR)
    monkeypatch.setenv("NUMBA_CACHE_DIR", "")  # recorded, so that what choose_kernel_cache sets is undone after
    monkeypatch.delenv("NUMBA_CACHE_DIR")  # (a later process would otherwise compile into this test's folder)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(kernel_cache, "sources_writable", lambda: False)
    assert kernel_cache.choose_kernel_cache() == tmp_path / "vtolpose" / "numba"
    assert os.environ["NUMBA_CACHE_DIR"] == str(tmp_path / "vtolpose" / "numba") == numba.core.config.CACHE_DIR


def test_a_writable_tree_or_a_given_cache_is_left_as_it_is(monkeypatch, tmp_path):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setattr(kernel_cache, "sources_writable", lambda: True)
    assert kernel_cache.choose_kernel_cache() is None and "NUMBA_CACHE_DIR" not in os.environ
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(kernel_cache, "sources_writable", lambda: False)
    assert kernel_cache.choose_kernel_cache() == tmp_path


def test_swapped_kernels_run_interpreted_and_come_back_compiled():
    from vtolpose.estimator import propagation_kernel as kernel
    from vtolpose.estimator.inertial import sample_kernel
    from vtolpose.estimator import filter as estimator_filter
    from vtolpose.service.runtime import kernel_swap

    compiled_step, compiled_level = kernel.step, sample_kernel.level_run
    try:
        assert kernel_swap.to_interpreted() > 0
        assert kernel.step is compiled_step.py_func and kernel_swap.compiled_of(kernel.step) is compiled_step
        assert estimator_filter.level_run is compiled_level.py_func  # a name imported from a kernel module
        n, v3 = 15, np.array([0.1, -0.2, 0.3])
        results = []
        for step in (kernel.step, compiled_step):
            F, out = np.eye(n), np.empty(kernel.OUT_LEN)
            results.append((step(v3, v3, np.array([1.0, 0.0, 0.0, 0.0]), v3 * 0.01, v3 * 0.1, v3 * 0.01, v3, 0.01, 9.8,
                                 F, np.eye(n), np.eye(n) * 1e-6, True, out), F, out))
        for interpreted, compiled in zip(*results):
            assert np.array_equal(interpreted, compiled)
    finally:
        kernel_swap.to_compiled()
    assert kernel.step is compiled_step and sample_kernel.level_run is compiled_level
    assert estimator_filter.level_run is compiled_level


@pytest.mark.slow
def test_a_cold_cache_gives_the_same_trajectory_at_once_and_fills_itself(tmp_path):
    """The program with an empty cache replays at once (interpreted) and leaves a background compiler; once it
    has finished (``warmup`` waits for it) the compiled replay writes the same bytes."""
    from vtolpose.drivers.simulator import simulate_flight
    from vtolpose.drivers.simulator.export import write_flight

    write_flight(simulate_flight("book", 12.0, 3), tmp_path / "book")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))

    def vtolpose(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "vtolpose", *args], env=env, capture_output=True, text=True,
                              check=True, timeout=600)

    def replay(out: Path) -> str:
        return vtolpose("replay", str(tmp_path / "book"), "--sensors", "imu,gps", "--no-progress", "--out", str(out)).stdout

    cold = replay(tmp_path / "cold.txt")
    assert "kernels interpreted while they compile in the background" in cold
    assert "compiled already" in vtolpose("warmup").stdout  # waited for the background compiler, then loaded
    warm = replay(tmp_path / "warm.txt")
    assert "kernels loaded from the cache" in warm
    assert (tmp_path / "cold.txt").read_bytes() == (tmp_path / "warm.txt").read_bytes()


def test_the_background_compiler_holds_the_lock_it_was_handed(tmp_path, monkeypatch):
    """The command takes the compile lock and hands it to the compiler it starts: while that compiler runs, the
    lock is taken (whoever waits for it waits for the compiler), even after the command let go of its copy; once
    the compiler ends, the lock is free. A second start meanwhile finds the lock taken and starts nothing."""
    import time

    from vtolpose.service.runtime import kernels

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    release, said = tmp_path / "release", tmp_path / "said"
    compiler = ("import os, sys, time\n"
                "from vtolpose.service.runtime.kernels import LOCK_FD_ENV, compile_lock\n"
                "handed = LOCK_FD_ENV in os.environ\n"
                "with compile_lock(block=False) as held:\n"
                f"    open({str(said)!r}, 'w').write(f'handed {{handed}} held {{held}}')\n"
                f"    while not os.path.exists({str(release)!r}):\n"
                "        time.sleep(0.02)\n")
    monkeypatch.setattr(kernels, "COMPILE_COMMAND", (sys.executable, "-c", compiler))
    started = kernels._start_compiler()
    assert started is not None
    try:
        with kernels.compile_lock(block=False) as free:
            assert not free
        assert kernels._start_compiler() is None  # one compiler at a time
    finally:
        release.touch()
        started.wait(timeout=60)
    assert started.returncode == 0
    assert said.read_text() == "handed True held True"
    with kernels.compile_lock(block=False) as free:
        assert free
    assert kernels.LOCK_FD_ENV not in os.environ
