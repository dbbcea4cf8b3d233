"""The estimator: pure computation, no I/O, no asyncio, no globals, deterministic for its input.

Sub-packages, in the order data flows through them:
``core`` (rotations, state, the Kalman update, frames, measurement and calibration types),
``inertial`` (IMU deltas, propagation, static and in-motion start-up, stillness, levelling),
``gnss`` (the GPS update), ``vision`` (camera model, features, association, inverse-depth
landmarks, map management, the camera update and its per-frame pipeline) and ``calibration``
(Allan deviation, IMU, chessboard, camera-IMU time offset, GPS latency and lever arm); beside them
``mapping`` (LIDAR returns placed with their poses, the height grid, volume and coverage).
On top of them: ``filter`` (one estimator: start-up, propagation, updates), ``fusion`` (late
measurements fused at their own time, the output predictor), ``health`` (sensor liveness,
divergence, resets), ``pose_history`` (what the mapper queries) and ``metrics`` (scores
against truth).
"""
