"""Zenoh session settings shared by the service and the mapper's client (no estimator imports).

Secure by default (docs/zenoh.md): a session listens only on the endpoints it is given (never
Zenoh's own default of a random port on every interface), and finds no peers by multicast or
gossip unless asked. The service adds its own access control (:func:`service_config`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import zenoh

if TYPE_CHECKING:  # the mapper's client builds its settings by hand and never loads the configuration
    from vtolpose.config.sections import ZenohSection

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7448"  # outputs.zenoh.listen's default: loopback only


@dataclass(slots=True)
class ZenohSettings:
    """Session settings (``outputs.zenoh.*``); the same for the service and the client."""

    mode: str = "peer"
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    multicast_scouting: bool = False
    root_ca_certificate: str | None = None
    certificate: str | None = None
    private_key: str | None = None
    mutual_tls: bool = False
    config_file: str | None = None  # a Zenoh JSON5 configuration applied first (ACL, authentication, …)

    @classmethod
    def from_section(cls, zenoh_section: ZenohSection) -> "ZenohSettings":
        peer = zenoh_section.mode == "peer"  # a client never listens (the default endpoint is a peer's)
        tls = zenoh_section.tls
        return cls(
            mode=zenoh_section.mode, listen=list(zenoh_section.listen) if peer else [],
            connect=list(zenoh_section.connect), multicast_scouting=zenoh_section.multicast_scouting,
            root_ca_certificate=tls.root_ca_certificate, certificate=tls.certificate, private_key=tls.private_key,
            mutual_tls=tls.mutual, config_file=zenoh_section.config_file,
        )

    def to_zenoh(self) -> zenoh.Config:
        conf = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        if self.mode == "peer":  # always explicit: an empty list listens nowhere
            conf.insert_json5("listen/endpoints", json.dumps(self.listen))
        if self.connect:
            conf.insert_json5("connect/endpoints", json.dumps(self.connect))
        # Multicast lets any host on the network find and join the session; gossip makes this
        # session connect to peers that others tell it about. Both only when asked.
        conf.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        conf.insert_json5("scouting/gossip/enabled", json.dumps(self.multicast_scouting))
        tls = {
            "root_ca_certificate": self.root_ca_certificate,
            # One certificate and key serve both directions: this node's identity.
            "listen_certificate": self.certificate, "listen_private_key": self.private_key,
            "connect_certificate": self.certificate, "connect_private_key": self.private_key,
        }
        for key, value in tls.items():
            if value is not None:
                conf.insert_json5(f"transport/link/tls/{key}", json.dumps(value))
        if self.mutual_tls:
            conf.insert_json5("transport/link/tls/enable_mtls", "true")
        return conf

    def endpoints_text(self) -> str:
        """Where this session listens and connects, for messages."""
        parts = [f"listening on {', '.join(self.listen)}" if self.listen else "listening nowhere"] if self.mode == "peer" else []
        if self.connect:
            parts.append(f"connecting to {', '.join(self.connect)}")
        return "; ".join(parts) or "no endpoints"


# Message kinds only the vehicle's own session may produce under its prefix. Refused when they
# arrive from any other session, so the vehicle never routes a rogue's poses or answers to its
# clients (a client connected to the vehicle has no other way in).
SERVICE_ONLY_MESSAGES = ("put", "delete", "declare_queryable", "reply", "liveliness_token")


def service_acl(prefix: str) -> dict[str, Any]:
    """The access-control rule the service adds: nobody else publishes or answers under ``prefix``."""
    return {
        "rule": {"id": "vtolpose-service-only", "permission": "deny", "flows": ["ingress"],
                 "messages": list(SERVICE_ONLY_MESSAGES), "key_exprs": [prefix, f"{prefix}/**"]},
        "subject": {"id": "vtolpose-any-remote"},  # no property: every remote session
        "policy": {"id": "vtolpose-service-only", "rules": ["vtolpose-service-only"], "subjects": ["vtolpose-any-remote"]},
    }


def service_config(settings: ZenohSettings, prefix: str, queryables: list[str], max_queries_per_s: float) -> zenoh.Config:
    """The service's session: ``settings``, plus its access control (merged into any from
    ``config_file``) and a per-link rate limit on incoming queries to each of ``queryables``."""
    conf = settings.to_zenoh()
    acl = json.loads(conf.get_json("access_control"))
    mine = service_acl(prefix)
    if not acl.get("enabled"):  # none configured: allow everything except what the rule denies
        acl = {"enabled": True, "default_permission": "allow", "rules": [], "subjects": [], "policies": []}
    for part, plural in (("rule", "rules"), ("subject", "subjects"), ("policy", "policies")):
        acl[plural] = list(acl.get(plural) or []) + [mine[part]]
    conf.insert_json5("access_control", json.dumps(acl))
    # Zenoh's downsampling interceptor keeps a limiter per link: each client connection gets its own.
    limits = json.loads(conf.get_json("downsampling")) or []
    limits.append({"id": "vtolpose-query-rate", "flows": ["ingress"], "messages": ["query"],
                   "rules": [{"key_expr": key, "freq": float(max_queries_per_s)} for key in queryables]})
    conf.insert_json5("downsampling", json.dumps(limits))
    return conf
