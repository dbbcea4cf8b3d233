"""pymavlink's ``mavutil`` speaking MAVLink 2 (INTERFACES.md), however it was first imported.

pymavlink picks its wire version from the ``MAVLINK20`` environment variable when ``mavutil`` is
first imported; a module that imported it earlier without the variable leaves MAVLink 1 in place,
so the dialect is reloaded here if needed. MAVLink 2 links still parse MAVLink 1 messages.
"""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

__all__ = ["ensure_mavlink2", "mavutil"]


def ensure_mavlink2() -> None:
    """Reload the dialect as MAVLink 2 if ``mavutil`` was imported before ``MAVLINK20`` was set."""
    if mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":
        os.environ["MAVLINK20"] = "1"
        mavutil.set_dialect(mavutil.current_dialect)


ensure_mavlink2()
