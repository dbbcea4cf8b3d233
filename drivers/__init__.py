"""Drivers: devices and files turned into typed, time-stamped samples in SI units; no estimation.

``imu`` (Crossbow IMU400CC framing and serial driver), ``gps`` (NMEA and MAVLink receivers,
geodetic → local NED), ``camera`` (libdc1394 for the Marlin, OpenCV for anything else),
``files`` (the dataset layout, CSV, TUM, dataset.yaml, LIDAR returns, the EuRoC importer), ``links`` (serial
ports and the MAVLink 2 wire), ``simulator`` (flights with exact truth, and their LIDAR) and ``emulators``
(the devices on pseudo-terminals, for tests).
"""
