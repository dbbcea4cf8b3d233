"""Smoothing: poses that also use the measurements after their time (Rauch–Tung–Striebel).

Owns what the backward pass needs from the forward filter and the backward pass itself, all
pure: :mod:`.recorder` (hooked where the filter propagates and updates, it emits one
:class:`~.steps.Step` per IMU propagation: posterior, transition, prediction of the robot error
state, and splits the record into segments wherever something other than a propagation or a
measurement update changed the state), :mod:`.rts` (the backward pass over those steps, batched
per chunk), :mod:`.fixed_lag` (the same pass over a short window, in bounded slices, for the
live daemon) and :mod:`.full_state` (the exact smoother with the landmarks kept, the yardstick
for the robot-block approximation). Storing steps on disk and wiring into the daemon is the
service's business.
"""
