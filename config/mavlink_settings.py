"""The MAVLink output's settings: its links (``outputs.mavlink.url`` and ``outputs.mavlink.endpoints``),
the autopilot's limits on the ODOMETRY rate, and the signing key files, checked before anything opens.

``url`` is the flight controller's link (the form every earlier configuration used, with
``signing_key_file`` and ``require_signing`` beside it); ``endpoints`` adds more links, each a
mapping ``{name, url, role, rate_hz, signing_key_file, require_signing}`` with ``role`` either
``autopilot`` or ``ground_station``. Why the rate limits are what they are: docs/mavlink.md.

The autopilot's GPS (``sensors.gps.type: mavlink``) is read from ``sensors.gps.mavlink_url`` with its own
``signing_key_file`` and ``require_signing``, or, when that URL is the flight controller's link, from that
link, whose signing settings then apply (the GPS's own may only repeat them, never differ).
"""

from __future__ import annotations

import math
import re
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from vtolpose.config.sections import MavlinkSection, build_section

__all__ = ["AUTOPILOT_RATES", "EndpointSpec", "OUTPUT_SCHEMES", "check_gps_link", "check_mavlink", "gps_shared_link",
           "key_file_problem", "mavlink_endpoints", "parse_mavlink_url"]

OUTPUT_SCHEMES = ("udpin", "udp", "udpout", "tcp")  # udp is udpin, as pymavlink reads it
NOT_SERVED = ("udpbcast", "tcpin")
# ODOMETRY rate [Hz] each autopilot's receiving side handles: (lowest, highest, default).
AUTOPILOT_RATES: dict[str, tuple[float, float, float]] = {
    "px4": (30.0, 50.0, 50.0),  # PX4's external-vision guide: 30-50 Hz
    "ardupilot": (5.0, 40.0, 30.0),  # EKF3 takes at most one per 20 ms; sends are spaced >= 21 ms
    "generic": (0.0, 1000.0, 50.0),
}
GROUND_STATION_RATE_HZ = 10.0
ROLES = ("autopilot", "ground_station")
ENDPOINT_KEYS = ("name", "url", "role", "rate_hz", "signing_key_file", "require_signing")
_HOST = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.\-]+)$")


def parse_mavlink_url(url: str) -> tuple[str, int | None]:
    """``(device, baud)``: ``udpin|udp|udpout|tcp:HOST:PORT`` (baud None), or ``/dev/ttyX[,BAUD]``."""
    scheme, sep, rest = url.partition(":")
    if sep and scheme in OUTPUT_SCHEMES:
        host, colon, port = rest.rpartition(":")
        if not colon or not host or not _HOST.match(host):
            raise ValueError(f"expected HOST:PORT after {scheme}:, got {rest!r}")
        if not port.isdigit() or not 1 <= int(port) <= 65535:
            raise ValueError(f"port {port!r} is not a number in 1..65535")
        return url, None
    if sep and scheme in NOT_SERVED:
        raise ValueError(f"{url!r}: {scheme} is not served by the MAVLink output; listen with udpin:HOST:PORT")
    if url.startswith("/") or re.match(r"^COM\d+", url):
        device, comma, baud = url.partition(",")
        if comma and (not baud.isdigit() or int(baud) <= 0):
            raise ValueError(f"serial baud rate {baud!r} is not a positive integer")
        return device, int(baud) if comma else None
    raise ValueError(f"{url!r} is not a MAVLink link: use {'|'.join(OUTPUT_SCHEMES)}:HOST:PORT or /dev/ttyX,BAUD")


def key_file_problem(path: str | Path) -> str | None:
    """Why a signing key file cannot be used (missing, or readable by every user), or None."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except OSError as exc:
        return f"file {path}: {exc.strerror or exc}"
    if not stat.S_ISREG(mode):
        return f"{path} is not a file"
    if mode & (stat.S_IROTH | stat.S_IWOTH):
        return (f"file {path} is readable or writable by every user (mode {stat.S_IMODE(mode):04o}): "
                f"anyone on this machine could sign as the vehicle; restrict it, e.g. chmod 600 {path}")
    return None


@dataclass(frozen=True, slots=True)
class EndpointSpec:
    name: str
    url: str
    role: str  # autopilot | ground_station
    rate_hz: float
    signing_key_file: str | None
    require_signing: bool
    key: str  # the configuration key it came from, for messages


def _rate_problem(rate: float, autopilot: str) -> str | None:
    low, high, _ = AUTOPILOT_RATES[autopilot]
    if not (low <= rate <= high):
        why = {"px4": "PX4 expects external vision at 30-50 Hz",
               "ardupilot": "ArduPilot's EKF3 drops external navigation closer than 20 ms apart"}.get(autopilot, "")
        return f"{rate:g} Hz is outside {low:g}..{high:g} Hz for autopilot {autopilot}" + (f" ({why})" if why else "")
    return None


def mavlink_endpoints(mavlink: MavlinkSection) -> list[EndpointSpec]:
    """Every configured link, the flight controller's ``url`` first; ValueError('KEY: problem') when one is wrong."""
    fc_rate = AUTOPILOT_RATES[mavlink.autopilot][2] if mavlink.rate_hz is None else mavlink.rate_hz
    specs = []
    if mavlink.url is not None:
        specs.append(EndpointSpec("flight_controller", mavlink.url, "autopilot", fc_rate, mavlink.signing_key_file,
                                  mavlink.require_signing, "outputs.mavlink"))
    for i, item in enumerate(mavlink.endpoints):
        key = f"outputs.mavlink.endpoints[{i}]"
        if not isinstance(item, dict):
            raise ValueError(f"{key}: expected a mapping {{name, url, role, ...}}, got {item!r}")
        unknown = sorted(set(item) - set(ENDPOINT_KEYS))
        if unknown:
            raise ValueError(f"{key}: unknown key(s) {unknown}; allowed: {', '.join(ENDPOINT_KEYS)}")
        for field in ("name", "url"):
            if not isinstance(item.get(field), str) or not item[field]:
                raise ValueError(f"{key}.{field}: expected a non-empty string, got {item.get(field)!r}")
        role = item.get("role", "ground_station")
        if role not in ROLES:
            raise ValueError(f"{key}.role: must be one of {', '.join(ROLES)}, got {role!r}")
        default_rate = fc_rate if role == "autopilot" else GROUND_STATION_RATE_HZ
        rate_i = item.get("rate_hz", default_rate)
        rate_i = default_rate if rate_i is None else rate_i
        if isinstance(rate_i, bool) or not isinstance(rate_i, (int, float)) or not math.isfinite(rate_i) or rate_i <= 0:
            raise ValueError(f"{key}.rate_hz: expected a number greater than 0, got {rate_i!r}")
        key_file = item.get("signing_key_file")
        if key_file is not None and (not isinstance(key_file, str) or not key_file):
            raise ValueError(f"{key}.signing_key_file: expected a file name or null, got {key_file!r}")
        require = item.get("require_signing", False)
        if not isinstance(require, bool):
            raise ValueError(f"{key}.require_signing: expected true or false, got {require!r}")
        specs.append(EndpointSpec(item["name"], item["url"], role, float(rate_i), key_file, require, key))
    return specs


def _mavlink_section(cfg: dict[str, Any]) -> MavlinkSection:
    return build_section(MavlinkSection, cfg, "outputs.mavlink")


def check_mavlink(cfg: dict[str, Any], fail: Callable[[str, str], Exception]) -> None:
    """Raise ``fail(key, problem)`` for the first MAVLink setting that cannot work."""
    try:
        specs = mavlink_endpoints(_mavlink_section(cfg))
    except ValueError as exc:
        key, _, problem = str(exc).partition(": ")
        raise fail(key, problem) from None
    enabled = cfg["outputs.mavlink.enabled"]
    if enabled and not specs:
        raise fail("outputs.mavlink.url", "no link: set a url or add outputs.mavlink.endpoints")
    names = set()
    for spec in specs:
        is_url = spec.key == "outputs.mavlink"
        url_key = "outputs.mavlink.url" if is_url else f"{spec.key}.url"
        try:
            parse_mavlink_url(spec.url)
        except ValueError as exc:
            raise fail(url_key, str(exc)) from None
        if spec.name in names:
            raise fail(f"{spec.key}.name", f"{spec.name!r} is used twice (the url link is 'flight_controller')")
        names.add(spec.name)
        if spec.role == "autopilot":
            problem = _rate_problem(spec.rate_hz, cfg["outputs.mavlink.autopilot"])
            if problem is not None:
                raise fail("outputs.mavlink.rate_hz" if is_url else f"{spec.key}.rate_hz", problem)
        if spec.require_signing and spec.signing_key_file is None:
            raise fail(f"{spec.key}.require_signing", f"needs {spec.key}.signing_key_file")
        if enabled and spec.signing_key_file is not None:
            problem = key_file_problem(spec.signing_key_file)
            if problem is not None:
                raise fail(f"{spec.key}.signing_key_file", problem)
    check_gps_link(cfg, fail)


def gps_shared_link(cfg: dict[str, Any]) -> EndpointSpec | None:
    """The output's flight-controller link the MAVLink GPS is read from (same URL), or None for a link of its own."""
    if not cfg["outputs.mavlink.enabled"]:
        return None
    primary = next((spec for spec in mavlink_endpoints(_mavlink_section(cfg)) if spec.role == "autopilot"), None)
    return primary if primary is not None and primary.url == cfg["sensors.gps.mavlink_url"] else None


def check_gps_link(cfg: dict[str, Any], fail: Callable[[str, str], Exception]) -> None:
    """Raise ``fail(key, problem)`` for a ``sensors.gps`` MAVLink setting that cannot work (type mavlink only)."""
    if cfg["sensors.gps.type"] != "mavlink":
        return
    url, key_file, require = (cfg[f"sensors.gps.{k}"] for k in ("mavlink_url", "signing_key_file", "require_signing"))
    if require and key_file is None:
        raise fail("sensors.gps.require_signing", "needs sensors.gps.signing_key_file")
    shared = gps_shared_link(cfg)
    if shared is not None:
        here = f"the GPS is read from the flight controller's link ({url}), checked with {shared.key}'s signing settings"
        if key_file is not None and key_file != shared.signing_key_file:
            raise fail("sensors.gps.signing_key_file", f"{here}: set {shared.key}.signing_key_file, not this")
        if require and not shared.require_signing:
            raise fail("sensors.gps.require_signing", f"{here}: set {shared.key}.require_signing: true")
        return
    scheme = url.partition(":")[0]
    if scheme in ("udpout", *NOT_SERVED):
        why = "binds no port to receive on" if scheme == "udpout" else "is not served"
        raise fail("sensors.gps.mavlink_url", f"{url!r}: {scheme} {why}; the GPS link receives on udpin:HOST:PORT, "
                                              "tcp:HOST:PORT or a serial port")
    try:
        parse_mavlink_url(url)
    except ValueError as exc:
        raise fail("sensors.gps.mavlink_url", str(exc)) from None
    if key_file is not None:
        problem = key_file_problem(key_file)
        if problem is not None:
            raise fail("sensors.gps.signing_key_file", problem)
