"""``--mcap FILE``: one MCAP file with the live view, every estimate, the raw samples and the status.

Written by foxglove-sdk's MCAP writer (zstd chunks, with an index, so Foxglove seeks in it):

- the scene of the live view (``foxglove.py``: ``/tf``, ``/pose``, ``/path``, ``/covariance``,
  ``/gps``, ``/gps/local``, ``/landmarks``, ``/camera/image``, ``/camera/overlay``, ``/status``);
- ``/vtolpose/pose``: every published estimate as the JSON document of ``<prefix>/pose`` (NED,
  covariance, quality, status), what ``vtolpose export`` reads the per-point quality from;
- the raw samples as ROS 2 messages in CDR (``ros2msg`` schemas, so ROS tools and Foxglove decode
  them): ``/imu`` (``sensor_msgs/Imu``, body FLU), ``/gps/fix`` (``sensor_msgs/NavSatFix``, the fix
  back in WGS84 around the NED origin) and ``/camera/image_raw/compressed``
  (``sensor_msgs/CompressedImage``, lossless PNG).

Log times are sensor times. Encoding and writing run on a background thread (``ViewWorker``), so
the recording never delays a pose; a sample it had to drop (queue full) is counted in the status.
The file must not exist yet: a recording is never overwritten. The
NED origin goes into the file's ``vtolpose`` metadata record when it closes.
"""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path
from typing import Any, Callable

import cv2
import foxglove
from foxglove.mcap import MCAPWriteOptions
import numpy as np
import pymap3d

from vtolpose.estimator import CameraFrame, FrameFeatures, FrameReport, GpsFix, ImuSample, OutputPose
from vtolpose.service.outputs import ros2_msgs
from vtolpose.service.outputs.foxglove import FoxgloveScene, Landmarks, Origin
from vtolpose.service.outputs.view_worker import ViewWorker
from vtolpose.service.outputs.pose_json import PoseJson

log = logging.getLogger(__name__)

POSE_TOPIC = "/vtolpose/pose"
IMU_TOPIC, GPS_TOPIC, IMAGE_TOPIC = "/imu", "/gps/fix", "/camera/image_raw/compressed"


def _ros_channel(context: foxglove.Context, topic: str, typename: str) -> foxglove.Channel:
    schema = foxglove.Schema(name=typename, encoding="ros2msg", data=ros2_msgs.message_definition(typename).encode())
    return foxglove.Channel(topic, schema=schema, message_encoding="cdr", context=context)


class McapOutput:
    """Records the scene, the estimates and the raw samples into ``path`` (see the module docstring)."""

    name = "mcap"

    def __init__(self, path: str | Path, rate_hz: float, path_points: int,
                 origin: Callable[[], Origin] = lambda: None, landmarks: Landmarks | None = None) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"{self.path}: already exists; an MCAP recording is never overwritten, choose a new file")
        self.origin = origin
        self.landmarks = landmarks
        self.context = foxglove.Context()
        self.scene = FoxgloveScene(self.context, origin, rate_hz, path_points)
        self.worker = ViewWorker("mcap-recorder")
        self.poses = foxglove.Channel(POSE_TOPIC, context=self.context)
        self.imu = _ros_channel(self.context, IMU_TOPIC, ros2_msgs.IMU)
        self.gps = _ros_channel(self.context, GPS_TOPIC, ros2_msgs.NAV_SAT_FIX)
        self.camera = _ros_channel(self.context, IMAGE_TOPIC, ros2_msgs.COMPRESSED_IMAGE)
        self.writer: Any = None
        self.error: str | None = None  # why the file could not be finished (a full disk), if so
        self._seq = 0
        self._pose_json = PoseJson()  # the worker's: json.dumps(pose_message(...)) in less of the interpreter's time
        self.counts = {"estimates": 0, "imu": 0, "gps": 0, "frames": 0}

    def open(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # One compression thread, the writer's own: zstd on every core would starve the niced camera workers.
        self.writer = foxglove.open_mcap(self.path, context=self.context,
                                         writer_options=MCAPWriteOptions(compression_threads=0))
        self.worker.start()
        log.info("recording estimates, raw samples and the view into %s", self.path)

    @property
    def incomplete(self) -> str | None:
        """Why the recording lacks what it was given (a write or the close failed), or None."""
        if self.error is not None:
            return self.error
        failures = self.worker.stats["failures"]
        return f"{failures} item(s) could not be written, the last: {self.worker.stats['last_failure']}" if failures else None

    @property
    def stats(self) -> dict[str, Any]:
        return {**self.counts, **self.worker.stats}

    # Called on the runtime's loop: hand over, never encode here.
    def publish(self, pose: OutputPose) -> None:
        if self.writer is not None:
            self._seq += 1
            self.worker.submit(self._estimate, pose, self._seq, self.origin())

    def publish_status(self, status: dict[str, Any]) -> None:
        if self.writer is not None:
            self.worker.submit(self.scene.status, status)

    def on_sample(self, sample: Any) -> None:
        """A raw sample as the runtime received it (before any calibrated time offset)."""
        if self.writer is not None:
            self.worker.submit(self._raw, sample, self.origin())

    def on_frame(self, image: np.ndarray | None, features: FrameFeatures, report: FrameReport) -> None:
        if self.writer is not None:
            points = self.landmarks()[1] if self.landmarks is not None else None  # read on the filter's loop
            self.worker.submit(self.scene.frame, image, features, report, points)

    # On the worker thread.
    def _estimate(self, pose: OutputPose, seq: int, origin: Origin) -> None:
        self.poses.log(self._pose_json(pose, seq, origin), log_time=pose.t_ns)
        self.counts["estimates"] += 1
        self.scene.pose(pose)

    def _raw(self, sample: Any, origin: Origin) -> None:
        if isinstance(sample, ImuSample):
            self.imu.log(ros2_msgs.serialize(ros2_msgs.imu(sample, "base_link"), ros2_msgs.IMU), log_time=sample.t_ns)
            self.counts["imu"] += 1
        elif isinstance(sample, GpsFix):
            if origin is not None:  # a NavSatFix needs latitude and longitude; without an origin there are none
                lat, lon, alt = (float(x) for x in pymap3d.ned2geodetic(*sample.p_ned, *origin))
                msg = ros2_msgs.nav_sat_fix(sample.t_ns, "gps", lat, lon, alt, sample.sigma_h, sample.sigma_v)
                self.gps.log(ros2_msgs.serialize(msg, ros2_msgs.NAV_SAT_FIX), log_time=sample.t_ns)
                self.counts["gps"] += 1
            self.scene.gps(sample)
        elif isinstance(sample, CameraFrame):
            ok, png = cv2.imencode(".png", sample.image)
            if ok:
                msg = ros2_msgs.compressed_image(sample.t_ns, "camera", png.tobytes(), "png")
                self.camera.log(ros2_msgs.serialize(msg, ros2_msgs.COMPRESSED_IMAGE), log_time=sample.t_ns)
                self.counts["frames"] += 1

    async def serve(self, stop: asyncio.Event) -> None:
        await stop.wait()

    def close(self) -> None:
        if self.writer is None:
            return
        self.worker.stop()
        origin = self.origin()
        writer, self.writer = self.writer, None
        try:
            writer.write_metadata("vtolpose", {
                "frame": "poses in /vtolpose/pose: local NED, body FRD; everything else REP 103 (map ENU, base_link FLU)",
                "origin_lat_lon_alt": "" if origin is None else ",".join(repr(float(x)) for x in origin),
            })
            writer.close()
        except Exception as exc:  # the SDK's own error (a full disk): the file is incomplete, said in the summary
            self.error = f"{getattr(exc, 'strerror', None) or exc}"
            raise
