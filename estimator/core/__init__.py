"""Core types and maths every other part uses: rotations (Hamilton quaternions, SO(3)), the
filter state with its error-state covariance, the one Kalman update, frame conversions at the
edges, the typed measurement samples and the calibration of the sensor set.
"""
