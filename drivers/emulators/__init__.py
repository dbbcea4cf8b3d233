"""Software stand-ins for the real devices, on pseudo-terminals, so the real drivers can be tested.

An emulator owns the master side of a pty; the driver under test opens ``emulator.port`` (the
slave, e.g. ``/dev/pts/7``) with pyserial exactly as it would open ``/dev/ttyUSB0``.
"""

from vtolpose.drivers.emulators.imu400 import Imu400Emulator
from vtolpose.drivers.emulators.nmea import NmeaEmulator, NmeaEpoch
from vtolpose.drivers.emulators.pty_device import PtyDevice

__all__ = ["Imu400Emulator", "NmeaEmulator", "NmeaEpoch", "PtyDevice"]
