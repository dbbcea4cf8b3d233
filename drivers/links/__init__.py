"""Byte links shared by the device drivers: host-timestamped serial reads with reopen back-off,
pymavlink held to MAVLink 2, and the MAVLink links' own transports, framing and signature checks
(non-blocking, bounded; nothing from a link is used before it passes :mod:`.mavlink_frames`).
"""
