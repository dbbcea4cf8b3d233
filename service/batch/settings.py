"""What every flight of a batch is run with, and the fingerprint that says whether a flight must run again.

The fingerprint of a flight is a SHA-256 over its input files' contents (names and bytes, in a
fixed order), the batch settings (the whole validated configuration, the sensor set, the map and
import options, the contents of any calibration or mounting file they name) and the vtolpose
version. A flight whose output folder holds the same fingerprint is done and is not run again.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

HASH_CHUNK = 1 << 20


@dataclass(frozen=True)
class EurocImport:
    """How an ASL/EuRoC folder becomes a dataset (``vtolpose import euroc``'s options)."""

    gps_rate_hz: float | None = None
    gps_sigma_m: float = 0.02
    seed: int = 0
    mounting: str | None = None
    camera: bool = True


@dataclass(frozen=True)
class BagImport:
    """How a ROS 2 bag becomes a dataset (``vtolpose import rosbag``'s options)."""

    imu_topic: str | None = None
    gps_topic: str | None = None
    image_topic: str | None = None
    truth_topic: str | None = None
    calibration: str | None = None
    fix_sigma: tuple[float, float] | None = None


@dataclass(frozen=True)
class BatchSettings:
    """The settings every flight of one batch shares (sent to each task, so small and picklable)."""

    cfg: dict[str, Any]
    sensors: tuple[str, ...] | None = None  # None: the configuration's replay.sensors
    score_from_s: float = 0.0
    cell_m: float = 1.0
    base_up_m: float = 0.0
    plots: bool = True  # the map's height PNG (needs matplotlib)
    euroc: EurocImport = field(default_factory=EurocImport)
    bag: BagImport = field(default_factory=BagImport)

    def fingerprint_doc(self) -> dict:
        """The settings as the fingerprint sees them: files they name by their contents."""
        from vtolpose import __version__

        doc = asdict(self)
        for section, key in (("euroc", "mounting"), ("bag", "calibration")):
            name = doc[section][key]
            if name is not None:
                doc[section][key] = {"file": Path(name).name, "sha256": file_digest(Path(name))}
        doc["vtolpose"] = __version__
        return doc


def file_digest(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(HASH_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def input_digest(path: Path) -> str:
    """SHA-256 over every file under ``path`` (or of the file): relative names, sizes and bytes."""
    digest = hashlib.sha256()
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    for item in files:
        rel = item.name if item == path else item.relative_to(path).as_posix()
        digest.update(f"{rel}\0{item.stat().st_size}\0".encode())
        with open(item, "rb") as f:
            while chunk := f.read(HASH_CHUNK):
                digest.update(chunk)
    return digest.hexdigest()


def flight_fingerprint(path: str | os.PathLike, settings: BatchSettings) -> str:
    """The fingerprint of one flight under ``settings`` (module docstring)."""
    digest = hashlib.sha256()
    digest.update(input_digest(Path(path)).encode())
    digest.update(json.dumps(settings.fingerprint_doc(), sort_keys=True, default=str).encode())
    return digest.hexdigest()
