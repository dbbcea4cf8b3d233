"""LIDAR mapping as pure computation: where a return lands, the height grid, and its scores.

``geometry`` turns one return (its own time, beam angle, range) and the pose at that time into
a point in local NED; ``height_grid`` accumulates points into a height map that grows with the
surveyed area, scan by scan, so a live mapper and a post-flight one build the same map; ``survey``
scores a map against a known ground (height RMSE, the volume above a base level, coverage).
What places the returns (a trajectory file, the service over Zenoh) lives in the service.
"""
