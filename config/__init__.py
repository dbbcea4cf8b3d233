"""Configuration: ``default.yaml`` merged with a user file, validated before anything opens.

Errors name the file, the key and the problem, and suggest the key that was probably meant.
"""

from __future__ import annotations

import copy
import difflib
import math
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from vtolpose.config.outputs import check_outputs
from vtolpose.config.schema import SCHEMA, Field

__all__ = ["ConfigError", "load_config", "default_config", "get", "validate"]


class ConfigError(ValueError):
    """A configuration that must not be used; the message says which key and why."""


def _read_yaml(text: str, origin: str) -> dict:
    try:
        data = yaml.safe_load(text)
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


def _check(key: str, value: Any, field: Field, origin: str) -> Any:
    def fail(problem: str) -> ConfigError:
        return ConfigError(f"{origin}: key '{key}': {problem} (got {value!r}, a {_type_name(value)})")

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


def _cross_checks(cfg: dict[str, Any], origin: str) -> None:
    if cfg["smoothing.fixed_lag_s"] > 0 and cfg["smoothing.max_window_s"] <= cfg["smoothing.fixed_lag_s"]:
        raise ConfigError(f"{origin}: key 'smoothing.max_window_s' must exceed 'smoothing.fixed_lag_s' "
                          "(the smoother needs the lag's worth of steps and some to work on)")
    check_outputs(cfg, origin)


def load_config(path: str | Path | None = None, overrides: dict | None = None) -> dict[str, Any]:
    """Defaults, then the file at ``path``, then ``overrides`` (nested dict); returns flat keys."""
    tree = default_config()
    validate(tree, "config/default.yaml")
    origin = "defaults"
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"config file {path}: not found")
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError as exc:
            raise ConfigError(f"config file {path}: not UTF-8 text (byte {exc.start}: {exc.reason})") from None
        user = _read_yaml(text, f"config file {path}")
        validate(user, f"config file {path}")
        tree = _merge(tree, user)
        origin = f"config file {path}"
    if overrides:
        validate(overrides, "command line")
        tree = _merge(tree, overrides)
    cfg = validate(tree, origin)
    _cross_checks(cfg, origin)
    return cfg


def get(cfg: dict[str, Any], prefix: str) -> dict[str, Any]:
    """The keys under ``prefix`` (without it): ``get(cfg, 'estimator.init')['max_wait_s']``."""
    start = prefix + "."
    return {k[len(start):]: v for k, v in cfg.items() if k.startswith(start)}
