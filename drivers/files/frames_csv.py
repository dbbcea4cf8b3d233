"""The EuRoC image index ``cam0/data.csv`` (``#timestamp [ns],filename``) and the images it names.

Same tolerance as the numeric tables (``vtolpose.drivers.files.csvio``): a malformed or out-of-order line is
skipped and counted with one warning naming the first; a missing or unreadable image is a
counted skip with a warning naming the file, so a replay never stops for one bad frame.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from vtolpose.drivers.files.csvio import parse_time_ns

log = logging.getLogger(__name__)

FRAMES_HEADER = "#timestamp [ns],filename"


def read_frame_index(csv_path: Path, image_dir: Path) -> tuple[list[tuple[int, Path]], int]:
    """``[(t_ns, image path)]`` in time order, and the number of lines skipped."""
    try:
        lines = csv_path.read_text(encoding="utf-8-sig", errors="replace").splitlines()
    except FileNotFoundError:
        raise FileNotFoundError(f"{csv_path}: file not found (expected {FRAMES_HEADER})") from None
    frames: list[tuple[int, Path]] = []
    bad: list[tuple[int, str, str]] = []
    last = None
    for number, line in enumerate(lines, start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = [f.strip() for f in stripped.split(",")]
        if len(fields) != 2 or not fields[1]:
            bad.append((number, line, f"{len(fields)} fields instead of 2"))
            continue
        try:
            t_ns = parse_time_ns(fields[0])
        except ValueError as exc:
            bad.append((number, line, str(exc)))
            continue
        name = Path(fields[1])
        if name.is_absolute() or ".." in name.parts:
            bad.append((number, line, "file name must be inside the image folder"))
            continue
        if last is not None and t_ns <= last:
            bad.append((number, line, "time not after the previous line"))
            continue
        last = t_ns
        frames.append((t_ns, image_dir / name))
    if bad:
        number, line, reason = bad[0]
        log.warning("%s: skipped %d malformed line(s); first is line %d (%s): %r", csv_path, len(bad), number, reason, line[:120])
    return frames, len(bad)


def load_grey(path: Path) -> np.ndarray | None:
    """A grey uint8 image, or None (with a warning naming the file) if it is missing or unreadable.

    Colour images are converted to grey; 16-bit images keep their top 8 bits.
    """
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
    if image is None:
        log.warning("%s: image %s, frame skipped", path, "missing" if not path.exists() else "unreadable")
        return None
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    return image


def write_frame_index(csv_path: Path, t_ns: list[int]) -> None:
    """The index of images written as ``<t_ns>.png`` in the folder beside it."""
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    lines = [FRAMES_HEADER, *(f"{t},{t}.png" for t in t_ns)]
    csv_path.write_text("\n".join(lines) + "\n", encoding="utf-8", newline="\n")


def write_png(path: Path, image: np.ndarray) -> None:
    ok, data = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise OSError(f"{path}: could not encode the image as PNG")
    path.write_bytes(data.tobytes())
