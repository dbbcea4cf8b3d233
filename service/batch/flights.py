"""Which flights a batch runs: the paths and globs given, each recognised by its layout.

A flight is a dataset folder (``dataset.yaml``), an ASL/EuRoC folder (``mav0/`` without a
``dataset.yaml``), a rosbag2 folder (``metadata.yaml``) or an MCAP file. A path that is none of
these is still a flight, one that fails with the reason, so a batch over a folder of recordings
lists the odd one out instead of stopping or skipping it silently.
"""

from __future__ import annotations

import glob
import re
from dataclasses import dataclass
from pathlib import Path

KINDS = ("dataset", "euroc", "rosbag")


@dataclass(frozen=True, slots=True)
class FlightInput:
    """One flight to process: its name (the output folder's), where it is, and how to read it."""

    name: str
    path: str
    kind: str  # one of KINDS, or "unknown" (the flight fails with ``problem``)
    problem: str | None = None


def flight_kind(path: Path) -> tuple[str, str | None]:
    """``(kind, problem)`` of ``path``: problem is None for a recognised recording."""
    if path.is_file():
        if path.suffix == ".mcap":
            return "rosbag", None
        return "unknown", f"{path}: not a recording (a file must be an MCAP bag, *.mcap)"
    if not path.is_dir():
        return "unknown", f"{path}: no such file or folder"
    if (path / "dataset.yaml").is_file():
        return "dataset", None
    if (path / "mav0").is_dir():
        return "euroc", None
    if (path / "metadata.yaml").is_file():
        return "rosbag", None
    return "unknown", (f"{path}: not a recording (expected a dataset folder with dataset.yaml, an ASL/EuRoC folder "
                       "with mav0/, a rosbag2 folder with metadata.yaml, or an .mcap file)")


def _stem(path: Path) -> str:
    stem = path.stem if path.is_file() else path.name
    return re.sub(r"[^A-Za-z0-9._-]+", "_", stem).strip("._") or "flight"


def find_flights(patterns: list[str]) -> list[FlightInput]:
    """The flights named by ``patterns`` (paths or globs), in the order given, each once.

    A glob that matches nothing is an error (a typo would otherwise make an empty batch); names
    are made unique by appending ``-2``, ``-3``, ... in that order."""
    paths: list[Path] = []
    for pattern in patterns:
        if glob.has_magic(pattern):
            matches = sorted(glob.glob(pattern))
            if not matches:
                raise ValueError(f"{pattern}: the pattern matches no file or folder")
            paths.extend(Path(m) for m in matches)
        else:
            paths.append(Path(pattern))
    seen_paths: set[Path] = set()
    used: set[str] = set()
    flights: list[FlightInput] = []
    for path in paths:
        key = path.resolve()
        if key in seen_paths:
            continue
        seen_paths.add(key)
        name, n = _stem(path), 1
        while name in used:
            n += 1
            name = f"{_stem(path)}-{n}"
        used.add(name)
        kind, problem = flight_kind(path)
        flights.append(FlightInput(name, str(path), kind, problem))
    if not flights:
        raise ValueError("no flights given")
    return flights
