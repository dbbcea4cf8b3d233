"""vtolpose: the onboard pose estimator of a VTOL UAV (IMU, camera and GPS fused by EKF-SLAM).

Everything installs under this one name: ``vtolpose.estimator`` (pure computation),
``vtolpose.drivers`` (devices and files), ``vtolpose.service`` (the daemon and the command
line) and ``vtolpose.config`` (defaults and validation). A LIDAR mapper needs only
``vtolpose.client``.
"""

__version__ = "0.1.0"
