"""Checks of the output links (Zenoh endpoints and prefix, key files; MAVLink in :mod:`.mavlink`) before anything opens.

The schema checks types; these check what a type cannot: a port in range, an endpoint a
Zenoh session can open, a key expression without wildcards, files that exist when the output
that needs them is enabled. Each error names the key.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any, Callable

log = logging.getLogger(__name__)

from vtolpose.config.mavlink_settings import check_mavlink

ZENOH_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
ZENOH_OTHER_PROTOCOLS = ("unixsock-stream", "serial")
ZENOH_ENCRYPTED_PROTOCOLS = ("tls", "quic")  # the protocols that use outputs.zenoh.tls.*
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


def zenoh_prefix(prefix: str | None, vehicle_name: str) -> str:
    """The key prefix: ``outputs.zenoh.prefix``, default ``vtolpose/<vehicle.name>``."""
    return prefix or f"vtolpose/{vehicle_name}"


def _protocol(endpoint: str) -> str:
    return endpoint.partition("/")[0]


def check_outputs(cfg: dict[str, Any], origin: str | Callable[..., str]) -> None:
    """Raise ConfigError naming the key of the first output setting that cannot work.

    ``origin``: where the values came from, or a :class:`vtolpose.config.Provenance` that names the
    source of the keys involved (a check across keys blames the one given last).
    """
    from vtolpose.config import ConfigError

    where = origin if callable(origin) else (lambda *keys: str(origin))

    def fail(key: str, problem: str, *related: str) -> ConfigError:
        return ConfigError(f"{where(key, *related)}: key '{key}': {problem}")

    check_mavlink(cfg, fail)
    for key, listen in (("outputs.zenoh.listen", True), ("outputs.zenoh.connect", False)):
        for endpoint in cfg[key]:
            try:
                check_zenoh_endpoint(endpoint, listen)
            except ValueError as exc:
                raise fail(key, str(exc)) from None
    # The default listen endpoint is a peer's; a client ignores it, but one set by hand is a mistake.
    if cfg["outputs.zenoh.mode"] == "client" and cfg["outputs.zenoh.listen"] and where("outputs.zenoh.listen") != "defaults":
        raise fail("outputs.zenoh.listen", "a client does not listen; use mode: peer, or connect to a router",
                   "outputs.zenoh.mode")
    prefix_key = "outputs.zenoh.prefix" if cfg["outputs.zenoh.prefix"] is not None else "vehicle.name"
    try:
        check_key_prefix(zenoh_prefix(cfg["outputs.zenoh.prefix"], cfg["vehicle.name"]))
    except ValueError as exc:
        raise fail(prefix_key, f"as the Zenoh key prefix: {exc}") from None
    if cfg["outputs.zenoh.enabled"]:
        for key in ("outputs.zenoh.config_file", *(f"outputs.zenoh.tls.{name}" for name in
                                                    ("root_ca_certificate", "certificate", "private_key"))):
            path = cfg[key]
            if path is not None and not Path(path).is_file():
                raise fail(key, f"file {path} not found")
        _check_zenoh_tls(cfg, fail)


def _check_zenoh_tls(cfg: dict[str, Any], fail: Callable[..., Exception]) -> None:
    """TLS files with only plain endpoints would run in plain text: refused; beside plain ones: a warning."""
    listen = cfg["outputs.zenoh.listen"] if cfg["outputs.zenoh.mode"] == "peer" else []
    endpoints = listen + cfg["outputs.zenoh.connect"]
    encrypted = [e for e in endpoints if _protocol(e) in ZENOH_ENCRYPTED_PROTOCOLS]
    plain = [e for e in endpoints if _protocol(e) not in ZENOH_ENCRYPTED_PROTOCOLS]
    if any(_protocol(e) == "tls" for e in encrypted) and cfg["outputs.zenoh.tls.root_ca_certificate"] is None:
        raise fail("outputs.zenoh.tls.root_ca_certificate", "tls/ endpoints need a root CA certificate",
                   "outputs.zenoh.listen", "outputs.zenoh.connect")
    tls_keys = [f"outputs.zenoh.tls.{name}" for name in ("root_ca_certificate", "certificate", "private_key")]
    given = [k for k in tls_keys if cfg[k] is not None] + (["outputs.zenoh.tls.mutual"] if cfg["outputs.zenoh.tls.mutual"] else [])
    if given and not encrypted:
        raise fail(given[0], f"TLS is configured but no endpoint is tls/ or quic/ ({', '.join(plain) or 'none'}): "
                   "the session would run in plain text; use tls/HOST:PORT endpoints",
                   *given[1:], "outputs.zenoh.listen", "outputs.zenoh.connect")
    if given and plain:
        log.warning("outputs.zenoh: TLS is configured, but %s %s plain text (not encrypted, not authenticated)",
                    ", ".join(plain), "is" if len(plain) == 1 else "are")
