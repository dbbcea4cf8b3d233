"""The estimator's numba kernels swapped for their interpreted functions, and back, in every vtolpose module.

The estimator calls its kernels through module attributes (``propagation_kernel.step_run(...)``, a name
imported from a kernel module, a kernel calling another through its module's globals), so replacing each
numba dispatcher there by the Python function it was compiled from makes every call plain Python, and putting the
dispatchers back makes them compiled again, between two calls of a running estimator.
"""

from __future__ import annotations

import sys
import types
from typing import Any, Callable

from numba.core.dispatcher import Dispatcher


_swapped: dict[tuple[str, str], Dispatcher] = {}  # (module, attribute) swapped out → its dispatcher, to put back


def compiled_of(function: Any) -> Dispatcher | None:
    """The dispatcher ``function`` stands in for while the kernels are interpreted; None for anything else."""
    return next((d for d in _swapped.values() if d.py_func is function), None)


def _vtolpose_modules() -> list[types.ModuleType]:
    return [m for name, m in list(sys.modules.items()) if name.startswith("vtolpose.") and m is not None]


def to_interpreted() -> int:
    """Every kernel interpreted: its module attribute becomes the plain function it compiles from (``py_func``),
    so a call costs no wrapper frame (a cold run makes ~170 000 of them). The kernel modules are imported first,
    so that none is left compiled. Returns how many module attributes were swapped."""
    from vtolpose.estimator import gps_kernel, propagation_kernel, rts_kernel, sample_kernel, update_kernel  # noqa: F401

    swapped = 0
    for module in _vtolpose_modules():
        for name, value in list(vars(module).items()):
            if isinstance(value, Dispatcher):
                _swapped[(module.__name__, name)] = value
                setattr(module, name, value.py_func)
                swapped += 1
    return swapped


def to_compiled() -> int:
    """Every kernel compiled again (each loads from the cache, or compiles, on its first call)."""
    restored = 0
    for (module_name, name), dispatcher in list(_swapped.items()):
        module = sys.modules.get(module_name)
        if module is not None and getattr(module, name, None) is dispatcher.py_func:
            setattr(module, name, dispatcher)
            restored += 1
        del _swapped[(module_name, name)]
    return restored


def compiled_view(function: Callable) -> Callable:
    """``function`` (a kernel module's ``warm_up``) seeing its module's kernels compiled while they are swapped
    out: so a watcher thread loads them while the estimator goes on with the interpreted ones."""
    module_name = function.__globals__.get("__name__")
    namespace = {name: _swapped.get((module_name, name), value) for name, value in function.__globals__.items()}
    return types.FunctionType(function.__code__, namespace, function.__name__, function.__defaults__,
                              function.__closure__)
