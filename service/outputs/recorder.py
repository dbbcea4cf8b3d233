"""Crash-safe flight recording into the dataset layout that ``vtolpose replay`` reads.

Raw samples go in as the devices gave them — IMU in sensor axes, GPS geodetic (WGS84), camera
frames as PNG — with ``dataset.yaml`` holding the calibration used live, so a recording replays
through exactly the conversions the live run made. Rows are appended and pushed to the
kernel (and, with ``fsync``, to the disk) at least every ``flush_interval_s`` by a background
thread: a SIGKILL loses at most that much, a power cut at worst leaves a torn last line that the
tolerant CSV reader skips. Any write error (a full disk) stops the recording with a loud status
and never raises into the caller: the estimator matters more than the log.
"""

from __future__ import annotations

import copy
import logging
import os
import threading
from dataclasses import replace
from pathlib import Path
from typing import IO, Any, Callable

import cv2
import numpy as np

from vtolpose.drivers.files.csvio import format_rows
from vtolpose.drivers.files.dataset import (
    CAM_CSV, CAM_DIR, GPS_CSV, GPS_HEADER_WGS84, GPS_SENSOR, GPS_WGS84_FORMATS, IMU_CSV, IMU_FORMATS, IMU_HEADER,
    dataset_yaml_text, gps_sensor_yaml,
)
from vtolpose.drivers.files.frames_csv import FRAMES_HEADER
from vtolpose.estimator import Calibration, CameraFrame

__all__ = ["CAM_HEADER", "FlightRecorder"]

log = logging.getLogger(__name__)

CAM_HEADER = FRAMES_HEADER  # EuRoC cam0/data.csv
# The dataset writer's number formats, so recordings and exports read alike.
_FORMATS = {IMU_CSV: IMU_FORMATS, GPS_CSV: GPS_WGS84_FORMATS}
_HEADERS = {IMU_CSV: IMU_HEADER, GPS_CSV: GPS_HEADER_WGS84, CAM_CSV: CAM_HEADER}


class FlightRecorder:
    """Appends raw samples to ``root``; thread-safe; ``status`` says whether it still records."""

    def __init__(
        self,
        root: str | Path,
        calibration: Calibration,
        *,
        name: str | None = None,
        description: str = "recorded by vtolpose",
        flush_interval_s: float = 1.0,
        fsync: bool = True,
        opener: Callable[..., IO[Any]] = open,
        on_status: Callable[[str], None] | None = None,
    ) -> None:
        self.root = Path(root)
        if (self.root / IMU_CSV).exists():
            raise FileExistsError(f"{self.root}: already holds a recording ({IMU_CSV}); choose a new folder")
        self.calibration = copy.deepcopy(calibration)  # the GPS origin may be filled in below
        self.name, self.description = name or self.root.name, description
        self.flush_interval_s, self.fsync = float(flush_interval_s), fsync
        self._open, self._on_status = opener, on_status
        self._lock = threading.RLock()
        self._files: dict[str, IO[Any]] = {}
        self._pending: dict[str, list[str]] = {}
        self._last_t: dict[str, int] = {}
        self.rows: dict[str, int] = {IMU_CSV: 0, GPS_CSV: 0, CAM_CSV: 0}
        self.dropped = 0           # samples not written because recording had stopped
        self.rejected: dict[str, int] = {}
        self.status = "recording"
        self._stop = threading.Event()
        self._guard(self._write_yaml)
        self._flusher = threading.Thread(target=self._flush_loop, name="recorder-flush", daemon=True)
        self._flusher.start()

    @property
    def ok(self) -> bool:
        return self.status == "recording"

    # -- samples --------------------------------------------------------------------------------
    def record_imu(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray) -> None:
        """One IMU sample in the *sensor's* axes (dataset.yaml's R_BI maps them to body)."""
        self._row(IMU_CSV, t_ns, np.concatenate([gyro, accel]))

    def record_gps(self, t_ns: int, lat_deg: float, lon_deg: float, alt_m: float, sigma_h: float, sigma_v: float,
                   origin: tuple[float, float, float] | None = None) -> None:
        """One geodetic fix. ``origin``: the live NED origin (e.g. the first fix), stored once in
        dataset.yaml so the replay converts around the same point."""
        if origin is not None and self.calibration.gps.origin_lla is None and self.ok:
            self.calibration.gps = replace(self.calibration.gps, origin_lla=tuple(map(float, origin)))
            self._guard(self._write_yaml)
        self._row(GPS_CSV, t_ns, np.array([lat_deg, lon_deg, alt_m, sigma_h, sigma_v]))

    def record_camera(self, frame: CameraFrame) -> None:
        """A frame as ``cam0/data/<t_ns>.png`` plus its line in ``cam0/data.csv``."""
        ok, png = cv2.imencode(".png", frame.image)  # outside the lock: IMU rows need not wait
        with self._lock:
            if not ok:
                self.rejected["camera_encode"] = self.rejected.get("camera_encode", 0) + 1
                return
            if not self._accept(CAM_CSV, frame.t_ns):
                return
            name = f"{frame.t_ns}.png"

            def write_png() -> None:
                path = self.root / CAM_DIR / name
                path.parent.mkdir(parents=True, exist_ok=True)
                with self._open(path, "wb") as f:
                    f.write(png.tobytes())

            if self._guard(write_png):
                self._queue(CAM_CSV, f"{frame.t_ns},{name}")

    # -- plumbing -------------------------------------------------------------------------------
    def _row(self, stream: str, t_ns: int, values: np.ndarray) -> None:
        with self._lock:
            if not self._accept(stream, t_ns):
                return
            try:
                line = format_rows(np.array([t_ns]), values.reshape(1, -1), _FORMATS[stream])[0]
            except ValueError:
                self.rejected["non_finite"] = self.rejected.get("non_finite", 0) + 1
                return
            self._queue(stream, line)

    def _accept(self, stream: str, t_ns: int) -> bool:
        if not self.ok:
            self.dropped += 1
            return False
        if t_ns <= self._last_t.get(stream, -1 << 63):
            self.rejected["out_of_order"] = self.rejected.get("out_of_order", 0) + 1
            return False
        self._last_t[stream] = t_ns
        return True

    def _queue(self, stream: str, line: str) -> None:
        self._pending.setdefault(stream, []).append(line + "\n")
        self.rows[stream] += 1

    def flush(self) -> None:
        """Write every queued row and push it to the kernel (and the disk, with ``fsync``)."""
        with self._lock:
            if self.ok:
                self._guard(self._flush_files)

    def _flush_files(self) -> None:
        for stream, lines in list(self._pending.items()):
            if not lines:
                continue
            f = self._files.get(stream) or self._open_stream(stream)
            f.write("".join(lines))
            lines.clear()
            f.flush()
            if self.fsync:
                os.fsync(f.fileno())

    def _open_stream(self, stream: str) -> IO[Any]:
        path = self.root / stream
        path.parent.mkdir(parents=True, exist_ok=True)
        if stream == GPS_CSV:
            self._write_atomic(self.root / GPS_SENSOR, gps_sensor_yaml("WGS84"))
        f = self._open(path, "a", encoding="utf-8", newline="\n")
        if f.tell() == 0:
            f.write(_HEADERS[stream] + "\n")
        self._files[stream] = f
        return f

    def _write_yaml(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        self._write_atomic(self.root / "dataset.yaml", dataset_yaml_text(self.calibration, self.name, self.description))

    def _write_atomic(self, path: Path, text: str) -> None:
        """Write beside, then rename: a crash leaves the old file or the new one, never half."""
        tmp = path.with_name(path.name + ".tmp")
        with self._open(tmp, "w", encoding="utf-8", newline="\n") as f:
            f.write(text)
            f.flush()
            if self.fsync:
                os.fsync(f.fileno())
        os.replace(tmp, path)

    def _guard(self, action: Callable[[], None]) -> bool:
        """Run a file operation; on any OSError stop recording loudly instead of raising."""
        try:
            action()
            return True
        except OSError as exc:
            self._fail(exc)
            return False

    def _fail(self, exc: OSError) -> None:
        where = f"{exc.filename}: " if exc.filename else ""
        self.status = f"stopped: {where}{exc.strerror or exc}"
        log.error("RECORDING STOPPED in %s: %s%s — the estimator keeps running, nothing more is recorded",
                  self.root, where, exc.strerror or exc)
        self._close_files()
        if self._on_status is not None:
            self._on_status(self.status)

    def _flush_loop(self) -> None:
        while not self._stop.wait(self.flush_interval_s):
            self.flush()

    def _close_files(self) -> None:
        for f in self._files.values():
            try:
                f.close()
            except OSError as exc:  # its write error is already in the recording's status; close the others
                log.debug("recording file %s close: %s", f.name, exc)
        self._files.clear()

    def close(self) -> None:
        """Flush what is queued and close the files (idempotent)."""
        self._stop.set()
        if self._flusher.is_alive() and self._flusher is not threading.current_thread():
            self._flusher.join(timeout=5.0)
        with self._lock:
            self.flush()
            self._close_files()
            if self.ok:
                self.status = "closed"

    def __enter__(self) -> "FlightRecorder":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def counts(self) -> dict[str, Any]:
        return {"status": self.status, "rows": {k.split("/")[1]: v for k, v in self.rows.items()},
                "dropped": self.dropped, "rejected": dict(self.rejected)}
