"""Zenoh session settings shared by the service and the mapper's client (no estimator imports)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

import zenoh


@dataclass(slots=True)
class ZenohSettings:
    """Session settings (``outputs.zenoh.*``); the same for the service and the client."""

    mode: str = "peer"
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    multicast_scouting: bool = True
    root_ca_certificate: str | None = None
    certificate: str | None = None
    private_key: str | None = None
    mutual_tls: bool = False

    @classmethod
    def from_config(cls, cfg: dict[str, Any]) -> "ZenohSettings":
        return cls(
            mode=cfg["outputs.zenoh.mode"], listen=list(cfg["outputs.zenoh.listen"]),
            connect=list(cfg["outputs.zenoh.connect"]), multicast_scouting=cfg["outputs.zenoh.multicast_scouting"],
            root_ca_certificate=cfg["outputs.zenoh.tls.root_ca_certificate"],
            certificate=cfg["outputs.zenoh.tls.certificate"], private_key=cfg["outputs.zenoh.tls.private_key"],
            mutual_tls=cfg["outputs.zenoh.tls.mutual"],
        )

    def to_zenoh(self) -> zenoh.Config:
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        if self.listen:
            conf.insert_json5("listen/endpoints", json.dumps(self.listen))
        if self.connect:
            conf.insert_json5("connect/endpoints", json.dumps(self.connect))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
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
