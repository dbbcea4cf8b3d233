"""The estimator: pure computation, no I/O, no asyncio, no globals, deterministic for its input.

Sub-packages, in the order data flows through them:
``core`` (rotations, state, the Kalman update, frames, measurement and calibration types),
``inertial`` (IMU deltas, propagation, static and in-motion start-up, stillness, levelling),
``gnss`` (the GPS update), ``vision`` (camera model, features, association, inverse-depth
landmarks, map management, the camera update and its per-frame pipeline) and ``calibration``
(Allan deviation, IMU, chessboard, camera-IMU time offset, GPS latency and lever arm); beside them
``mapping`` (LIDAR returns placed with their poses, the height grid, volume and coverage).
Public names: the service imports the estimator through ``vtolpose.estimator`` only (``_public.py`` lists them).
On top of them: ``filter`` (one estimator: start-up, propagation, updates), ``fusion`` (late
measurements fused at their own time, the output predictor), ``health`` (sensor liveness,
divergence, resets), ``pose_history`` (what the mapper queries) and ``metrics`` (scores
against truth).
"""

from importlib import import_module

from vtolpose.estimator._public import PUBLIC
from vtolpose.estimator.core.kernel_cache import choose_kernel_cache

choose_kernel_cache()  # before any kernel module imports numba, which reads it then

__all__ = sorted(PUBLIC)


def __getattr__(name: str):
    """A public name, its module loaded on first use (``vtolpose --help`` loads none of them)."""
    module = PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    owner = import_module(module)
    value = getattr(owner, name) if hasattr(owner, name) else import_module(f"{module}.{name}")
    globals()[name] = value
    return value
