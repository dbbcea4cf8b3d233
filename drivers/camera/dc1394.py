"""The Marlin F-080 (IIDC/DCAM over FireWire) through libdc1394 2.x, bound with ctypes.

Only what capture needs is bound: enumerate, choose the video mode (a standard IIDC mode with
its frame rate, or a Format_7 region whose isochronous packet size sets the frame rate),
DMA capture, release. Frame times are libdc1394's DMA-completion time (wall clock, µs) moved
onto the monotonic clock and moved back by the configured exposure/transfer latency.
Without the library or without a camera, :class:`CameraUnavailable` says so and how to go on.
Struct layouts follow ``dc1394/camera.h`` and ``dc1394/video.h`` of libdc1394 2.2.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import math
import select
import time
from ctypes import POINTER, Structure, byref, c_char_p, c_int, c_int32, c_uint16, c_uint32, c_uint64, c_void_p
from dataclasses import dataclass
from typing import Any

import numpy as np

from vtolpose.config.sections import CameraSection
from vtolpose.drivers.camera.common import CameraUnavailable
from vtolpose.estimator.core.measurements import CameraFrame

__all__ = [
    "CameraInfo", "Dc1394Camera", "Dc1394Config", "INSTALL_HINT", "VIDEO_MODES", "format7_packet_size",
    "list_cameras", "load_library",
]

log = logging.getLogger(__name__)

INSTALL_HINT = "apt-get install libdc1394-25"
_LIBRARY_NAMES = ("libdc1394.so.25", "libdc1394.so.22")

# Enumerations of libdc1394 2.x (dc1394/types.h, video.h, capture.h, log.h).
_MODE_NAMES = (
    "160x120_yuv444", "320x240_yuv422", "640x480_yuv411", "640x480_yuv422", "640x480_rgb8", "640x480_mono8",
    "640x480_mono16", "800x600_yuv422", "800x600_rgb8", "800x600_mono8", "1024x768_yuv422", "1024x768_rgb8",
    "1024x768_mono8", "800x600_mono16", "1024x768_mono16", "1280x960_yuv422", "1280x960_rgb8", "1280x960_mono8",
    "1600x1200_yuv422", "1600x1200_rgb8", "1600x1200_mono8", "1280x960_mono16", "1600x1200_mono16", "exif",
    *(f"format7_{i}" for i in range(8)),
)
VIDEO_MODES = {name: 64 + i for i, name in enumerate(_MODE_NAMES)}
_FRAMERATES = {1.875: 32, 3.75: 33, 7.5: 34, 15.0: 35, 30.0: 36, 60.0: 37, 120.0: 38, 240.0: 39}
_ISO_SPEED_400 = 2
_COLOR_MONO8, _COLOR_RAW8 = 352, 361
_CAPTURE_POLICY_POLL = 673
_CAPTURE_FLAGS_DEFAULT = 0x4
_ON, _OFF = 1, 0
_LOG_ERROR, _LOG_WARNING = 768, 769
_ISO_CYCLES_PER_S = 8000  # IEEE 1394 isochronous cycle: 125 µs


class _CameraId(Structure):
    _fields_ = [("unit", c_uint16), ("guid", c_uint64)]


class _CameraList(Structure):
    _fields_ = [("num", c_uint32), ("ids", POINTER(_CameraId))]


class _Camera(Structure):
    _fields_ = [
        ("guid", c_uint64), ("unit", c_int), ("unit_spec_ID", c_uint32), ("unit_sw_version", c_uint32),
        ("unit_sub_sw_version", c_uint32), ("command_registers_base", c_uint32), ("unit_directory", c_uint32),
        ("unit_dependent_directory", c_uint32), ("advanced_features_csr", c_uint64), ("PIO_control_csr", c_uint64),
        ("SIO_control_csr", c_uint64), ("strobe_control_csr", c_uint64), ("format7_csr", c_uint64 * 8),
        ("iidc_version", c_int), ("vendor", c_char_p), ("model", c_char_p), ("vendor_id", c_uint32),
        ("model_id", c_uint32), ("bmode_capable", c_int), ("one_shot_capable", c_int),
        ("multi_shot_capable", c_int), ("can_switch_on_off", c_int), ("has_vmode_error_status", c_int),
        ("has_feature_error_status", c_int), ("max_mem_channel", c_int), ("flags", c_uint32),
    ]


class _Frame(Structure):
    _fields_ = [
        ("image", POINTER(ctypes.c_ubyte)), ("size", c_uint32 * 2), ("position", c_uint32 * 2),
        ("color_coding", c_int), ("color_filter", c_int), ("yuv_byte_order", c_uint32), ("data_depth", c_uint32),
        ("stride", c_uint32), ("video_mode", c_int), ("total_bytes", c_uint64), ("image_bytes", c_uint32),
        ("padding_bytes", c_uint32), ("packet_size", c_uint32), ("packets_per_frame", c_uint32),
        ("timestamp", c_uint64), ("frames_behind", c_uint32), ("camera", POINTER(_Camera)), ("id", c_uint32),
        ("allocated_image_bytes", c_uint64), ("little_endian", c_int), ("data_in_padding", c_int),
    ]


_LOG_HANDLER = ctypes.CFUNCTYPE(None, c_int, c_char_p, c_void_p)
_SIGNATURES: dict[str, tuple[Any, list]] = {
    "dc1394_new": (c_void_p, []),
    "dc1394_free": (None, [c_void_p]),
    "dc1394_camera_enumerate": (c_int, [c_void_p, POINTER(POINTER(_CameraList))]),
    "dc1394_camera_free_list": (None, [POINTER(_CameraList)]),
    "dc1394_camera_new_unit": (POINTER(_Camera), [c_void_p, c_uint64, c_int]),
    "dc1394_camera_free": (None, [POINTER(_Camera)]),
    "dc1394_video_set_iso_speed": (c_int, [POINTER(_Camera), c_int]),
    "dc1394_video_set_mode": (c_int, [POINTER(_Camera), c_int]),
    "dc1394_video_set_framerate": (c_int, [POINTER(_Camera), c_int]),
    "dc1394_video_set_transmission": (c_int, [POINTER(_Camera), c_int]),
    "dc1394_format7_get_packet_parameters": (c_int, [POINTER(_Camera), c_int, POINTER(c_uint32), POINTER(c_uint32)]),
    "dc1394_format7_set_roi": (c_int, [POINTER(_Camera), c_int, c_int] + [c_int32] * 5),
    "dc1394_capture_setup": (c_int, [POINTER(_Camera), c_uint32, c_uint32]),
    "dc1394_capture_stop": (c_int, [POINTER(_Camera)]),
    "dc1394_capture_get_fileno": (c_int, [POINTER(_Camera)]),
    "dc1394_capture_dequeue": (c_int, [POINTER(_Camera), c_int, POINTER(POINTER(_Frame))]),
    "dc1394_capture_enqueue": (c_int, [POINTER(_Camera), POINTER(_Frame)]),
    "dc1394_error_get_string": (c_char_p, [c_int]),
    "dc1394_log_register_handler": (c_int, [c_int, _LOG_HANDLER, c_void_p]),
}
_library: ctypes.CDLL | None = None


@_LOG_HANDLER
def _log_to_python(kind: int, message: bytes, user: int) -> None:
    """libdc1394 prints to stderr by default; route its messages into our log instead."""
    text = (message or b"").decode("ascii", errors="replace").strip()
    log.log(logging.ERROR if kind == _LOG_ERROR else logging.WARNING, "libdc1394: %s", text)


def load_library() -> ctypes.CDLL:
    """libdc1394 with typed signatures (loaded once); CameraUnavailable if it is not installed."""
    global _library
    if _library is not None:
        return _library
    names = [n for n in (ctypes.util.find_library("dc1394"), *_LIBRARY_NAMES) if n]
    for name in names:
        try:
            lib = ctypes.CDLL(name)
        except OSError:
            continue
        for fn, (restype, argtypes) in _SIGNATURES.items():
            getattr(lib, fn).restype, getattr(lib, fn).argtypes = restype, argtypes
        for kind in (_LOG_ERROR, _LOG_WARNING):
            lib.dc1394_log_register_handler(kind, _log_to_python, None)
        _library = lib
        return lib
    raise CameraUnavailable(
        f"libdc1394 is not installed (tried {', '.join(names)}); install it ({INSTALL_HINT}) to use the "
        "IIDC/FireWire camera, or set sensors.camera.type to opencv or none")


def _check(lib: ctypes.CDLL, err: int, what: str) -> None:
    if err != 0:
        reason = (lib.dc1394_error_get_string(err) or b"?").decode("ascii", errors="replace")
        raise CameraUnavailable(f"libdc1394: {what} failed: {reason} (error {err})")


@dataclass(frozen=True, slots=True)
class CameraInfo:
    guid: int
    unit: int
    vendor: str
    model: str

    def describe(self) -> str:
        return f"{self.vendor} {self.model}, GUID {self.guid:016x} unit {self.unit}"


def _context(lib: ctypes.CDLL) -> int:
    ctx = lib.dc1394_new()
    if not ctx:
        raise CameraUnavailable("libdc1394 found no FireWire or USB bus it can use (is /dev/fw* present and "
                                "readable by this user?); set sensors.camera.required: false to run without")
    return ctx


def _camera_ids(lib: ctypes.CDLL, ctx: int) -> list[tuple[int, int]]:
    listing = POINTER(_CameraList)()
    _check(lib, lib.dc1394_camera_enumerate(ctx, byref(listing)), "listing cameras")
    try:
        return [(listing.contents.ids[i].guid, listing.contents.ids[i].unit) for i in range(listing.contents.num)]
    finally:
        lib.dc1394_camera_free_list(listing)


def list_cameras() -> list[CameraInfo]:
    """Every IIDC camera on the buses (an empty list when there is none)."""
    lib = load_library()
    ctx = _context(lib)
    try:
        out = []
        for guid, unit in _camera_ids(lib, ctx):
            cam = lib.dc1394_camera_new_unit(ctx, guid, unit)
            if cam:
                c = cam.contents
                out.append(CameraInfo(guid, unit, (c.vendor or b"?").decode(errors="replace"),
                                      (c.model or b"?").decode(errors="replace")))
                lib.dc1394_camera_free(cam)
        return out
    finally:
        lib.dc1394_free(ctx)


@dataclass(slots=True)
class Dc1394Config:
    guid: int | None = None      # None: the first camera found
    mode: str = "format7_0"
    width: int = 656             # Format_7 region (standard modes have their own size)
    height: int = 494
    fps: float = 7.5
    latency_s: float = 0.0
    dma_buffers: int = 4

    @classmethod
    def from_section(cls, camera: CameraSection, device: str | None = None) -> "Dc1394Config":
        text = device if device is not None else camera.device
        mode = camera.mode.lower()
        if mode not in VIDEO_MODES:
            raise ValueError(f"sensors.camera.mode: {mode!r} is not an IIDC mode; use one of {', '.join(VIDEO_MODES)}")
        return cls(None if text is None else int(str(text), 16), mode, camera.width, camera.height, camera.fps,
                   camera.latency_s)


def format7_packet_size(width: int, height: int, fps: float, unit_bytes: int, max_bytes: int) -> int:
    """Bytes per isochronous packet that deliver one mono8 frame every 1/fps s (Format_7 sets
    the frame rate through the packet size: one packet per 125 µs cycle)."""
    packets_per_frame = _ISO_CYCLES_PER_S / fps
    size = math.ceil(width * height / packets_per_frame)
    size = unit_bytes * math.ceil(size / unit_bytes) if unit_bytes > 0 else size
    return int(min(max(size, unit_bytes), max_bytes))


class Dc1394Camera:
    def __init__(self, config: Dc1394Config) -> None:
        self.config = config
        self._lib: ctypes.CDLL | None = None
        self._ctx = 0
        self._cam: Any = None
        self._capturing = False
        self.info: CameraInfo | None = None
        self.seq = 0
        self.failures = 0

    def open(self) -> str:
        cfg = self.config
        self._lib = lib = load_library()
        self._ctx = _context(lib)
        try:
            ids = _camera_ids(lib, self._ctx)
            if not ids:
                raise CameraUnavailable("no IIDC (FireWire) camera found: check its cable, power and the "
                                        "permissions on /dev/fw*; set sensors.camera.required: false to run without")
            chosen = [i for i in ids if cfg.guid is None or i[0] == cfg.guid]
            if not chosen:
                found = ", ".join(f"{g:016x}" for g, _ in ids)
                raise CameraUnavailable(f"no camera with GUID {cfg.guid:016x} (found {found})")
            guid, unit = chosen[0]
            self._cam = cam = lib.dc1394_camera_new_unit(self._ctx, guid, unit)
            if not cam:
                raise CameraUnavailable(f"libdc1394 could not open camera {guid:016x}")
            c = cam.contents
            self.info = CameraInfo(guid, unit, (c.vendor or b"?").decode(errors="replace"),
                                   (c.model or b"?").decode(errors="replace"))
            self._configure(lib, cam)
            _check(lib, lib.dc1394_capture_setup(cam, cfg.dma_buffers, _CAPTURE_FLAGS_DEFAULT), "DMA capture setup")
            self._capturing = True
            _check(lib, lib.dc1394_video_set_transmission(cam, _ON), "starting transmission")
        except BaseException:
            self.close()
            raise
        return self.describe()

    def _configure(self, lib: ctypes.CDLL, cam: Any) -> None:
        cfg = self.config
        mode = VIDEO_MODES[cfg.mode]
        _check(lib, lib.dc1394_video_set_iso_speed(cam, _ISO_SPEED_400), "setting 400 Mb/s")
        _check(lib, lib.dc1394_video_set_mode(cam, mode), f"setting mode {cfg.mode}")
        if cfg.mode.startswith("format7"):
            unit, most = c_uint32(), c_uint32()
            _check(lib, lib.dc1394_format7_get_packet_parameters(cam, mode, byref(unit), byref(most)),
                   "reading Format_7 packet limits")
            packet = format7_packet_size(cfg.width, cfg.height, cfg.fps, unit.value, most.value)
            _check(lib, lib.dc1394_format7_set_roi(cam, mode, _COLOR_MONO8, packet, 0, 0, cfg.width, cfg.height),
                   f"setting the {cfg.width} x {cfg.height} mono8 region")
        elif cfg.fps in _FRAMERATES:
            _check(lib, lib.dc1394_video_set_framerate(cam, _FRAMERATES[cfg.fps]), f"setting {cfg.fps} fps")
        else:
            raise CameraUnavailable(f"{cfg.fps} fps is not an IIDC frame rate for {cfg.mode}; use one of "
                                    f"{', '.join(map(str, _FRAMERATES))} or a format7 mode")

    def describe(self) -> str:
        who = self.info.describe() if self.info else "no camera"
        return f"libdc1394 {who}: mode {self.config.mode}, {self.config.width} x {self.config.height}, {self.config.fps:g} fps"

    def read(self, timeout_s: float = 0.5) -> CameraFrame | None:
        """The next frame (oldest first), or None if none arrived within ``timeout_s``."""
        lib, cam = self._lib, self._cam
        if not self._capturing or lib is None:
            return None
        readable, _, _ = select.select([lib.dc1394_capture_get_fileno(cam)], [], [], timeout_s)
        if not readable:
            return None
        frame_p = POINTER(_Frame)()
        if lib.dc1394_capture_dequeue(cam, _CAPTURE_POLICY_POLL, byref(frame_p)) != 0 or not frame_p:
            self.failures += 1
            return None
        try:
            f = frame_p.contents
            if f.color_coding not in (_COLOR_MONO8, _COLOR_RAW8):
                self.failures += 1
                return None
            width, height, stride = f.size[0], f.size[1], f.stride
            rows = np.frombuffer(ctypes.string_at(f.image, stride * height), dtype=np.uint8).reshape(height, stride)
            wall_minus_mono = time.time_ns() - time.monotonic_ns()
            t_ns = f.timestamp * 1000 - wall_minus_mono - int(round(self.config.latency_s * 1e9))
        finally:
            lib.dc1394_capture_enqueue(cam, frame_p)
        self.seq += 1
        return CameraFrame(int(t_ns), rows[:, :width].copy(), self.seq)

    def close(self) -> None:
        """Stop transmission and DMA, release the camera and the library context (idempotent)."""
        lib = self._lib
        if lib is not None and self._cam:
            if self._capturing:
                lib.dc1394_video_set_transmission(self._cam, _OFF)
                lib.dc1394_capture_stop(self._cam)
            lib.dc1394_camera_free(self._cam)
        if lib is not None and self._ctx:
            lib.dc1394_free(self._ctx)
        self._cam, self._ctx, self._capturing = None, 0, False

    def __enter__(self) -> "Dc1394Camera":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
