"""Configuration: ``default.yaml`` merged with a user file, validated before anything opens.

Errors name the file, the key and the problem, and suggest the key that was probably meant.
"""

from __future__ import annotations

import copy
import difflib
import math
import re
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from vtolpose.config.outputs import check_outputs
from vtolpose.config.schema import SCHEMA, Field
from vtolpose.config.yaml_limits import UnsafeYaml, load_bounded, read_bounded

__all__ = ["ConfigError", "Provenance", "load_config", "default_config", "get", "validate"]


class ConfigError(ValueError):
    """A configuration that must not be used; the message says which key and why."""


def _read_yaml(text: str, origin: str) -> dict:
    try:
        data = load_bounded(text)
    except UnsafeYaml as exc:
        raise ConfigError(f"{origin}: {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        raise ConfigError(f"{origin}: not valid YAML{where}: {getattr(exc, 'problem', exc)}") from None
    except RecursionError:  # PyYAML recurses per nesting level: '[[[[...' a thousand deep
        raise ConfigError(f"{origin}: nested too deeply to be a configuration") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{origin}: the top level must be a mapping of sections, got {type(data).__name__}")
    return data


def default_config() -> dict:
    text = resources.files(__name__).joinpath("default.yaml").read_text(encoding="utf-8")
    return _read_yaml(text, "config/default.yaml")


def _flatten(tree: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in tree.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict) and any(k.startswith(path + ".") for k in SCHEMA):
            out.update(_flatten(value, path + "."))
        else:
            out[path] = value
    return out


def _type_name(value: Any) -> str:
    return "null" if value is None else type(value).__name__


def _finite(x: int | float) -> bool:
    """Finite as a float: YAML integers have no size limit, and 10**400 is no float."""
    try:
        return math.isfinite(x)
    except OverflowError:
        return False


# YAML 1.1 (PyYAML) reads a number with an exponent but no point, such as 1e12, as text; YAML 1.2
# and people read it as a number. A float key takes it as the number it is, then checks its range.
_EXPONENT_NUMBER = re.compile(r"[-+]?[0-9]+(\.[0-9]*)?[eE][-+]?[0-9]+")


def _shown(value: Any, limit: int = 80) -> str:
    """``repr(value)`` cut to ``limit`` characters: an error message never echoes a huge value in full."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}… ({len(text)} characters)"


def _check(key: str, value: Any, field: Field, origin: str) -> Any:
    def fail(problem: str) -> ConfigError:
        return ConfigError(f"{origin}: key '{key}': {problem} (got {_shown(value)}, a {_type_name(value)})")

    if field.kind == "float" and isinstance(value, str) and _EXPONENT_NUMBER.fullmatch(value.strip()):
        value = float(value)

    if value is None:
        if field.nullable:
            return None
        raise fail("must not be null")
    kind = field.kind
    if kind == "bool":
        if not isinstance(value, bool):
            raise fail("expected true or false")
    elif kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise fail("expected an integer")
    elif kind == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not _finite(value):
            raise fail("expected a finite number")
        value = float(value)
    elif kind == "str":
        if not isinstance(value, str) or not value:
            raise fail("expected a non-empty string")
    elif kind == "list":
        if not isinstance(value, list):
            raise fail("expected a list")
        bad = [v for v in value if field.items and v not in field.items]
        if bad:
            raise fail(f"unknown item(s) {bad}; allowed: {', '.join(field.items)}")
    elif kind in ("vector3", "matrix3"):
        rows = value if kind == "matrix3" else [value]
        ok = isinstance(value, list) and len(rows) == (3 if kind == "matrix3" else 1)
        ok = ok and all(isinstance(r, list) and len(r) == 3 for r in rows)
        ok = ok and all(isinstance(x, (int, float)) and not isinstance(x, bool) and _finite(x) for r in rows for x in r)
        if not ok:
            raise fail("expected a list of 3 numbers" if kind == "vector3" else "expected 3 rows of 3 numbers")
    else:  # pragma: no cover - a schema typo
        raise ConfigError(f"schema error: key '{key}' has unknown kind {kind!r}")
    if field.choices and value not in field.choices:
        raise fail(f"must be one of {', '.join(map(str, field.choices))}")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if field.positive and value <= 0:
            raise fail("must be greater than 0")
        if field.minimum is not None and value < field.minimum:
            raise fail(f"must be at least {field.minimum}")
        if field.maximum is not None and value > field.maximum:
            raise fail(f"must be at most {field.maximum}")
    return value


def validate(tree: dict, origin: str) -> dict[str, Any]:
    """Check every key of ``tree`` against the schema; return the flat, normalised values."""
    flat = _flatten(tree)
    out = {}
    for key, value in flat.items():
        field = SCHEMA.get(key)
        if field is None and any(k.startswith(key + ".") for k in SCHEMA):
            raise ConfigError(f"{origin}: key '{key}': expected a section (a mapping of keys), got {value!r}")
        if field is None:
            hint = difflib.get_close_matches(key, SCHEMA.keys(), n=1)
            section = key.rsplit(".", 1)[0]
            known = sorted({k.rsplit(".", 1)[0] for k in SCHEMA})
            suggestion = f" (did you mean '{hint[0]}'?)" if hint else (
                "" if section in known else f" (known sections: {', '.join(sorted({k.split('.')[0] for k in SCHEMA}))})"
            )
            raise ConfigError(f"{origin}: unknown key '{key}'{suggestion}")
        out[key] = _check(key, value, field, origin)
    return out


def _merge(base: dict, override: dict) -> dict:
    merged = copy.deepcopy(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = _merge(merged[key], value)
        else:
            merged[key] = copy.deepcopy(value)
    return merged


class Provenance:
    """Where each key's value came from (defaults, the config file, the command line).

    A check across keys blames the source that gave the latest of their values: the one the user
    most likely just changed. ``str()`` is the last source loaded (for messages about one layer).
    """

    def __init__(self, layers: list[str], sources: dict[str, str]) -> None:
        self.layers = layers
        self.sources = sources

    def __call__(self, *keys: str) -> str:
        # An element of a list key (``outputs.mavlink.endpoints[1].url``) came with its list.
        given = [self.sources.get(k.split("[", 1)[0], self.layers[0]) for k in keys] or [self.layers[-1]]
        return max(given, key=self.layers.index)

    def __str__(self) -> str:
        return self.layers[-1]


def _cross_checks(cfg: dict[str, Any], where: Provenance) -> None:
    if cfg["smoothing.fixed_lag_s"] > 0 and cfg["smoothing.max_window_s"] <= cfg["smoothing.fixed_lag_s"]:
        raise ConfigError(f"{where('smoothing.max_window_s', 'smoothing.fixed_lag_s')}: key 'smoothing.max_window_s' "
                          f"({cfg['smoothing.max_window_s']:g} s) must exceed key 'smoothing.fixed_lag_s' "
                          f"({cfg['smoothing.fixed_lag_s']:g} s): the smoother needs the lag's worth of steps and some to work on")
    check_outputs(cfg, where)


def _read_config_file(path: Path) -> dict:
    if not path.is_file():
        raise ConfigError(f"config file {path}: not found")
    try:
        text = read_bounded(path)
    except UnsafeYaml as exc:
        raise ConfigError(f"config file {path}: {exc}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"config file {path}: not UTF-8 text (byte {exc.start}: {exc.reason})") from None
    return _read_yaml(text, f"config file {path}")


def load_config(path: str | Path | None = None, overrides: dict | None = None) -> dict[str, Any]:
    """Defaults, then the file at ``path``, then ``overrides`` (nested dict); returns flat keys."""
    tree = default_config()
    layers = ["defaults"]
    sources = dict.fromkeys(validate(tree, "config/default.yaml"), "defaults")
    if path is not None:
        path = Path(path)
        user = _read_config_file(path)
        layers.append(f"config file {path}")
        sources.update(dict.fromkeys(validate(user, layers[-1]), layers[-1]))
        tree = _merge(tree, user)
    if overrides:
        layers.append("command line")
        sources.update(dict.fromkeys(validate(overrides, layers[-1]), layers[-1]))
        tree = _merge(tree, overrides)
    where = Provenance(layers, sources)
    cfg = validate(tree, str(where))
    _cross_checks(cfg, where)
    return cfg


def get(cfg: dict[str, Any], prefix: str) -> dict[str, Any]:
    """The keys under ``prefix`` (without it): ``get(cfg, 'estimator.init')['max_wait_s']``."""
    start = prefix + "."
    return {k[len(start):]: v for k, v in cfg.items() if k.startswith(start)}
