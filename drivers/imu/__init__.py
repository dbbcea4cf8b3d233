"""The Crossbow IMU400CC: its 18-byte packet, framing a noisy byte stream, and the serial driver.
"""
