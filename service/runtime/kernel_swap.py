"""The estimator's numba kernels swapped for their interpreted functions, and back, in every vtolpose module.

The estimator calls its kernels through module attributes (``propagation_kernel.step_run(...)``, a name
imported from a kernel module, a kernel calling another through its module's globals), so replacing each
numba dispatcher there by an :class:`Interpreted` stand-in makes every call plain Python, and putting the
dispatchers back makes them compiled again, between two calls of a running estimator.
"""

from __future__ import annotations

import sys
import types
from typing import Any, Callable

from numba.core.dispatcher import Dispatcher


class Interpreted:
    """A kernel run as the Python function it was compiled from; otherwise its dispatcher (``py_func``,
    ``signatures``)."""

    __slots__ = ("dispatcher", "py_func")

    def __init__(self, dispatcher: Dispatcher) -> None:
        self.dispatcher = dispatcher
        self.py_func = dispatcher.py_func

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.py_func(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.dispatcher, name)


def _vtolpose_modules() -> list[types.ModuleType]:
    return [m for name, m in list(sys.modules.items()) if name.startswith("vtolpose.") and m is not None]


def to_interpreted() -> int:
    """Every kernel interpreted: their modules imported first, so that none is left compiled. Returns how many
    module attributes were swapped."""
    from vtolpose.estimator import gps_kernel, propagation_kernel, rts_kernel, sample_kernel, update_kernel  # noqa: F401

    swapped = 0
    for module in _vtolpose_modules():
        for name, value in list(vars(module).items()):
            if isinstance(value, Dispatcher):
                setattr(module, name, Interpreted(value))
                swapped += 1
    return swapped


def to_compiled() -> int:
    """Every kernel compiled again (each loads from the cache, or compiles, on its first call)."""
    restored = 0
    for module in _vtolpose_modules():
        for name, value in list(vars(module).items()):
            if isinstance(value, Interpreted):
                setattr(module, name, value.dispatcher)
                restored += 1
    return restored


def compiled_view(function: Callable) -> Callable:
    """``function`` (a kernel module's ``warm_up``) seeing its module's kernels compiled while they are swapped
    out: so a watcher thread loads them while the estimator goes on with the interpreted ones."""
    namespace = {name: value.dispatcher if isinstance(value, Interpreted) else value
                 for name, value in function.__globals__.items()}
    return types.FunctionType(function.__code__, namespace, function.__name__, function.__defaults__,
                              function.__closure__)
