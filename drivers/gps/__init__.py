"""GPS receivers: NMEA 0183 over serial and the autopilot's GPS over MAVLink, both giving local-NED fixes.
"""
