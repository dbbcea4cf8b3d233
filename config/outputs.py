"""Checks of the output links (Zenoh endpoints and prefix, key files; MAVLink in :mod:`.mavlink`) before anything opens.

The schema checks types; these check what a type cannot: a port in range, an endpoint a
Zenoh session can open, a key expression without wildcards, files that exist when the output
that needs them is enabled. Each error names the key.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from vtolpose.config.mavlink import check_mavlink

ZENOH_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
ZENOH_OTHER_PROTOCOLS = ("unixsock-stream", "serial")
_HOST = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.\-]+)$")


def _port(text: str, allow_zero: bool = False) -> int:
    if not text.isdigit() or not (0 if allow_zero else 1) <= int(text) <= 65535:
        raise ValueError(f"port {text!r} is not a number in {0 if allow_zero else 1}..65535")
    return int(text)


def _host_port(text: str, allow_zero: bool = False) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not _HOST.match(host):
        raise ValueError(f"expected HOST:PORT, got {text!r}")
    return host.strip("[]"), _port(port, allow_zero)


def check_zenoh_endpoint(endpoint: Any, listen: bool) -> None:
    """A Zenoh locator ``proto/address``, e.g. ``tcp/127.0.0.1:7447`` or ``tls/[::1]:7447``."""
    if not isinstance(endpoint, str):
        raise ValueError(f"endpoint {endpoint!r} is not a string")
    locator = re.split(r"[?#]", endpoint, maxsplit=1)[0]
    proto, sep, address = locator.partition("/")
    if not sep or not address:
        raise ValueError(f"endpoint {endpoint!r}: expected PROTOCOL/ADDRESS, e.g. tcp/127.0.0.1:7447")
    if proto in ZENOH_IP_PROTOCOLS:
        try:
            _host_port(address, allow_zero=listen)
        except ValueError as exc:
            raise ValueError(f"endpoint {endpoint!r}: {exc}") from None
    elif proto not in ZENOH_OTHER_PROTOCOLS:
        raise ValueError(f"endpoint {endpoint!r}: unknown protocol {proto!r} (use one of {', '.join(ZENOH_IP_PROTOCOLS)})")


def check_key_prefix(prefix: str) -> None:
    if prefix.startswith("/") or prefix.endswith("/") or "//" in prefix or re.search(r"[*$?#\s]", prefix):
        raise ValueError(f"{prefix!r} is not a plain Zenoh key (no wildcards, spaces or empty chunks)")


def zenoh_prefix(cfg: dict[str, Any]) -> str:
    """The configured key prefix, default ``vtolpose/<vehicle.name>``."""
    return cfg["outputs.zenoh.prefix"] or f"vtolpose/{cfg['vehicle.name']}"


def check_outputs(cfg: dict[str, Any], origin: str) -> None:
    """Raise ConfigError naming the key of the first output setting that cannot work."""
    from vtolpose.config import ConfigError

    def fail(key: str, problem: str) -> ConfigError:
        return ConfigError(f"{origin}: key '{key}': {problem}")

    check_mavlink(cfg, fail)
    for key, listen in (("outputs.zenoh.listen", True), ("outputs.zenoh.connect", False)):
        for endpoint in cfg[key]:
            try:
                check_zenoh_endpoint(endpoint, listen)
            except ValueError as exc:
                raise fail(key, str(exc)) from None
    if cfg["outputs.zenoh.mode"] == "client" and cfg["outputs.zenoh.listen"]:
        raise fail("outputs.zenoh.listen", "a client does not listen; use mode: peer, or connect to a router")
    prefix_key = "outputs.zenoh.prefix" if cfg["outputs.zenoh.prefix"] is not None else "vehicle.name"
    try:
        check_key_prefix(zenoh_prefix(cfg))
    except ValueError as exc:
        raise fail(prefix_key, f"as the Zenoh key prefix: {exc}") from None
    if cfg["outputs.zenoh.enabled"]:
        for name in ("root_ca_certificate", "certificate", "private_key"):
            path = cfg[f"outputs.zenoh.tls.{name}"]
            if path is not None and not Path(path).is_file():
                raise fail(f"outputs.zenoh.tls.{name}", f"file {path} not found")
        uses_tls = any(str(e).startswith("tls/") for e in cfg["outputs.zenoh.listen"] + cfg["outputs.zenoh.connect"])
        if uses_tls and cfg["outputs.zenoh.tls.root_ca_certificate"] is None:
            raise fail("outputs.zenoh.tls.root_ca_certificate", "tls/ endpoints need a root CA certificate")
