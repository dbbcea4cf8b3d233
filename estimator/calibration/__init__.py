"""Calibration maths (the thesis' missing chapter 5): Allan deviation, static IMU calibration and
the static stretches it needs, chessboard intrinsics, the camera-IMU time offset by
correlation, and the GPS latency and antenna lever arm. Results are plain values; the service
writes them out.
"""
