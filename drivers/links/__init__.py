"""Byte links shared by the device drivers: host-timestamped serial reads with reopen back-off,
and pymavlink held to MAVLink 2.
"""
