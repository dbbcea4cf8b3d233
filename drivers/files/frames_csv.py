"""The EuRoC image index ``cam0/data.csv`` (``#timestamp [ns],filename``) and the images it names.

Same tolerance as the numeric tables (``vtolpose.drivers.files.csvio``): a malformed or out-of-order line is
skipped and counted with one warning naming the first; a missing or unreadable image is a
counted skip with a warning naming the file, so a replay never stops for one bad frame.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from vtolpose.drivers.files.csvio import parse_time_ns

log = logging.getLogger(__name__)

FRAMES_HEADER = "#timestamp [ns],filename"


def read_frame_index(csv_path: Path, image_dir: Path, in_order: bool = True) -> tuple[list[tuple[int, Path]], int]:
    """``[(t_ns, image path)]`` in time order, and the number of lines skipped. ``in_order=False``: in file order,
    whatever the times (the caller undoes clock steps, then drops what is still out of order)."""
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
        if in_order and last is not None and t_ns <= last:
            bad.append((number, line, "time not after the previous line"))
            continue
        last = t_ns
        frames.append((t_ns, image_dir / name))
    if bad:
        number, line, reason = bad[0]
        log.warning("%s: skipped %d malformed line(s); first is line %d (%s): %r", csv_path, len(bad), number, reason, line[:120])
    return frames, len(bad)


MAX_FRAME_PIXELS = 16_000_000  # a camera frame is well under this; a decompression bomb is far above it
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _jpeg_size(f) -> tuple[int, int] | None:
    """Width and height from a JPEG's start-of-frame segment, walking the segments before it."""
    f.seek(2)
    while True:
        marker = f.read(2)
        if len(marker) < 2 or marker[0] != 0xFF:
            return None
        while marker[1] == 0xFF:  # fill bytes
            marker = marker[1:] + f.read(1)
        length = int.from_bytes(f.read(2), "big")
        if marker[1] in _JPEG_SOF:
            data = f.read(5)
            return (int.from_bytes(data[3:5], "big"), int.from_bytes(data[1:3], "big")) if len(data) == 5 else None
        if length < 2:
            return None
        f.seek(length - 2, 1)


def image_kind(path: Path) -> str | None:
    """``"png"``, ``"jpeg"``, ``"bmp"`` or ``"pnm"`` by the file's first bytes (not its name), else None."""
    with open(path, "rb") as f:
        head = f.read(8)
    if head.startswith(_PNG_SIGNATURE):
        return "png"
    if head.startswith(b"\xff\xd8"):
        return "jpeg"
    if head.startswith(b"BM"):
        return "bmp"
    return "pnm" if head[:2] in (b"P5", b"P6") else None


def image_size(path: Path) -> tuple[int, int] | None:
    """``(width, height)`` read from the header of a PNG, JPEG, BMP or binary PGM/PPM file, without
    decoding it; None for any other format or a header that does not parse."""
    with open(path, "rb") as f:
        head = f.read(32)
        if head.startswith(_PNG_SIGNATURE) and head[12:16] == b"IHDR":
            return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
        if head.startswith(b"\xff\xd8"):
            return _jpeg_size(f)
        if head.startswith(b"BM") and len(head) >= 26:
            return (abs(int.from_bytes(head[18:22], "little", signed=True)),
                    abs(int.from_bytes(head[22:26], "little", signed=True)))
        if head[:2] in (b"P5", b"P6"):
            fields = head[2:].split()
            if len(fields) >= 2 and fields[0].isdigit() and fields[1].isdigit():
                return int(fields[0]), int(fields[1])
    return None


def _refusal(path: Path, max_pixels: int) -> str | None:
    """Why the image at ``path`` must not be decoded, or None."""
    if not path.is_file():
        return "missing" if not path.exists() else "not a file"
    try:
        size = image_size(path)
    except OSError as exc:
        return f"unreadable ({exc.strerror or exc})"
    if size is None:
        return "not a PNG, JPEG, BMP or PGM/PPM image (or a damaged header)"
    width, height = size
    if width * height > max_pixels:
        return f"{width} x {height} pixels by its header, more than the {max_pixels} a frame may have: not decoded"
    return None


def load_grey(path: Path, max_pixels: int = MAX_FRAME_PIXELS) -> np.ndarray | None:
    """A grey uint8 image, or None (with a warning naming the file) if it is missing, unreadable, or
    larger than ``max_pixels`` by its header (checked before decoding: a small file can claim 20000²).

    Colour images are converted to grey; 16-bit images keep their top 8 bits.
    """
    import cv2  # on first use: a process that never needs OpenCV never loads it (~16 MB)

    problem = _refusal(path, max_pixels)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if problem is None else None
    if image is None:
        log.warning("%s: image %s, frame skipped", path, problem or "unreadable")
        return None
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    return image


def write_frame_index(csv_path: Path, t_ns: list[int], suffixes: list[str] | None = None) -> None:
    """The index of images written as ``<t_ns><suffix>`` in the folder beside it (``.png`` unless told)."""
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    suffixes = suffixes if suffixes is not None else [".png"] * len(t_ns)
    if len(suffixes) != len(t_ns):
        raise ValueError(f"write_frame_index: {len(t_ns)} times but {len(suffixes)} suffixes")
    lines = [FRAMES_HEADER, *(f"{t},{t}{x}" for t, x in zip(t_ns, suffixes))]
    csv_path.write_text("\n".join(lines) + "\n", encoding="utf-8", newline="\n")


def write_png(path: Path, image: np.ndarray) -> None:
    import cv2

    ok, data = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise OSError(f"{path}: could not encode the image as PNG")
    path.write_bytes(data.tobytes())
