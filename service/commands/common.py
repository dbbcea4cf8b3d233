"""Options shared by several subcommands: configuration file, overrides, sensor sets."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import yaml

from vtolpose.config import ConfigError, load_config
from vtolpose.config.yaml_limits import UnsafeYaml, load_bounded


def add_config_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE", help="YAML with the keys to change (see config/default.yaml)")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one key, e.g. --set estimator.variant=thesis (repeatable; VALUE is YAML)",
    )
    p.add_argument("--variant", choices=("thesis", "biases"), help="shorthand for --set estimator.variant=...")


def overrides_from(args: argparse.Namespace) -> dict[str, Any]:
    tree: dict[str, Any] = {}
    items = list(args.set)
    if getattr(args, "variant", None):
        items.append(f"estimator.variant={args.variant}")
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
        try:
            value = load_bounded(text)
        except (yaml.YAMLError, UnsafeYaml, RecursionError):
            raise ConfigError(f"--set {item[:80]!r}: VALUE is not valid YAML (or its aliases expand without bound)") from None
        node = tree
        parts = key.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {item!r}: '{part}' is set as a value and as a section")
        node[parts[-1]] = value
    return tree


def config_from(args: argparse.Namespace) -> dict[str, Any]:
    return load_config(args.config, overrides_from(args))


def parse_sensors(text: str | None) -> list[str] | None:
    if text is None:
        return None
    return [s.strip() for s in text.split(",") if s.strip()]


def write_json(path: str | Path, doc: dict) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=2, sort_keys=False) + "\n", encoding="utf-8")
