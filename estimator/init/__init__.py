"""Starting the filter in motion from the camera and the IMU, without GPS (visual-inertial initialisation).

A service restarted in the air has no still window to take roll, pitch and the gyro bias from,
and without GPS nothing fixes velocity or scale. ``tracks`` follows features from frame to
frame over a short window; ``window_solver`` recovers gravity, velocity, the biases and the
metric positions of the tracked points from those tracks and the IMU deltas between the
frames (a linear first guess, then a Gauss–Newton refinement whose information matrix gives
the covariance); ``visual_inertial`` decides when a solution has converged and turns it into
the EKF-SLAM's first state, landmarks included.
"""
