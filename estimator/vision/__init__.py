"""The camera side of EKF-SLAM: the radial-tangential camera model, point features and a cheap
frame check, data association inside gates, unified inverse-depth landmarks, map management,
the stacked camera update, and the pipeline that runs one frame through all of them.
"""
