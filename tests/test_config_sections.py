"""The typed sections match the schema key for key, and carry the validated values."""

from __future__ import annotations

import typing
from collections import Counter
from dataclasses import FrozenInstanceError, fields, is_dataclass

import pytest

from vtolpose.config import load_config
from vtolpose.config.schema import SCHEMA
from vtolpose.config.sections import ESTIMATOR_PREFIXES, GpsSection, Sections, build_section, build_sections


def section_keys(cls: type, prefix: str = "") -> list[str]:
    """The configuration key of every leaf field under ``cls``."""
    keys = []
    hints = typing.get_type_hints(cls)
    for f in fields(cls):
        key = f"{prefix}.{f.name}" if prefix else f.name
        keys += section_keys(hints[f.name], key) if is_dataclass(hints[f.name]) else [key]
    return keys


def test_every_key_has_exactly_one_section_field_or_is_the_estimators():
    keys = section_keys(Sections)
    assert [k for k, n in Counter(keys).items() if n > 1] == []
    assert sorted(set(keys) - set(SCHEMA)) == [], "a section field with no key in config/schema.py"
    left = sorted(k for k in SCHEMA if k not in keys and not k.startswith(ESTIMATOR_PREFIXES))
    assert left == [], "a key in config/schema.py that no section (nor the estimator's options) takes"
    assert [k for k in keys if k.startswith(ESTIMATOR_PREFIXES)] == []


def test_sections_carry_the_validated_values():
    cfg = load_config(None, {"sensors": {"gps": {"origin": [58.4, 15.6, 60]}},
                             "outputs": {"zenoh": {"connect": ["tcp/10.0.0.2:7447"]}}})
    sections = build_sections(cfg)
    assert sections.sensors.gps.origin == (58.4, 15.6, 60)
    assert sections.outputs.zenoh.connect == ("tcp/10.0.0.2:7447",)
    assert sections.outputs.zenoh.tls.mutual is cfg["outputs.zenoh.tls.mutual"]
    assert sections.sensors.imu.R_BI == tuple(tuple(row) for row in cfg["sensors.imu.R_BI"])
    assert sections.vehicle.system_id == cfg["vehicle.system_id"]
    with pytest.raises(FrozenInstanceError):
        sections.vehicle.system_id = 2  # type: ignore[misc]


def test_a_field_without_its_key_names_the_key():
    cfg = dict(load_config())
    del cfg["sensors.gps.uere_m"]
    with pytest.raises(KeyError, match="sensors.gps.uere_m"):
        build_section(GpsSection, cfg, "sensors.gps")
