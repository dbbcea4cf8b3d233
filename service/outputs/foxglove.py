"""Foxglove: the live 3-D view over WebSocket (``--foxglove [PORT]``), built with foxglove-sdk.

:class:`FoxgloveScene` turns what the runtime sees into Foxglove's well-known schemas on one SDK
context; :class:`FoxgloveOutput` serves that context to Foxglove over WebSocket, and the MCAP
recording (``mcap.py``) writes the same scene into a file. Everything is shown in REP 103 frames
(``map`` ENU, ``base_link`` FLU), converted once through :mod:`vtolpose.estimator.core.frames`.

Topics: ``/tf`` (map → base_link), ``/pose``, ``/path`` (the last ``path_points`` poses),
``/covariance`` (the 95 % position ellipsoid), ``/gps`` (each fix as latitude/longitude for the
map panel) and ``/gps/local`` (the fixes in ``map``), ``/landmarks`` (the EKF-SLAM map as points),
``/camera/image`` with ``/camera/overlay`` (features, predicted landmarks with their search
gates, accepted matches, new landmarks, a status line) and ``/status`` (the status document).
Poses are shown at ``rate_hz`` of sensor time and the path at 2 Hz. All encoding happens on a
background thread (:class:`~vtolpose.service.outputs.view_worker.ViewWorker`): the runtime's loop only queues what it hands over. Messages carry sensor time as their log
time, so a replay at any speed shows the flight's own clock. The server listens only on the
configured host (127.0.0.1 by default).
"""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from typing import Any, Callable

import cv2
import foxglove
import numpy as np
import pymap3d
from foxglove import channels as ch
from foxglove.messages import (
    CircleAnnotation, Color, CompressedImage, CubePrimitive, FrameTransform, FrameTransforms, ImageAnnotations,
    LocationFix, LocationFixPositionCovarianceType, Point2, PointsAnnotation, PointsAnnotationType, Pose,
    PoseInFrame, PosesInFrame, Quaternion, SceneEntity, SceneUpdate, SpherePrimitive, TextAnnotation, Timestamp, Vector3,
)

from vtolpose.estimator import (
    Estimator, FrameFeatures, FrameReport, GpsFix, ned_to_enu, OutputPose, pose_ned_frd_to_enu_flu, R_ENU_NED,
    rot_to_quat,
)
from vtolpose.service.outputs.view_worker import ViewWorker
from vtolpose.service.replay.overlay import working_picture

log = logging.getLogger(__name__)

Origin = tuple[float, float, float] | None
Landmarks = Callable[[], tuple[np.ndarray, np.ndarray]]  # (ids, points in NED)
CHI2_3DOF_95 = 7.8147  # the 95 % ellipsoid of a 3-D Gaussian is this many sigma² out
PATH_PERIOD_NS = 500_000_000
GPS_SHOWN = 300  # fixes kept in the local GPS trail
MAX_FEATURES_DRAWN = 3000
YELLOW, CYAN, GREEN, MAGENTA, RED, WHITE = (Color(r=r, g=g, b=b, a=1.0) for r, g, b in (
    (1.0, 0.86, 0.0), (0.0, 0.86, 1.0), (0.0, 0.9, 0.0), (1.0, 0.0, 1.0), (1.0, 0.0, 0.0), (1.0, 1.0, 1.0)))


def stamp(t_ns: int) -> Timestamp:
    sec, nsec = divmod(max(int(t_ns), 0), 1_000_000_000)
    return Timestamp(sec, nsec)


def _vec(v: np.ndarray) -> Vector3:
    return Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _quat(q_wxyz: np.ndarray) -> Quaternion:
    w, x, y, z = (float(c) for c in q_wxyz)
    return Quaternion(x=x, y=y, z=z, w=w)


def estimator_landmarks(est: Estimator) -> tuple[np.ndarray, np.ndarray]:
    """Ids and NED points of the landmarks in the filter state (those with a positive inverse depth).

    Read on the runtime's loop, where the filter runs, so the state is never half updated."""
    return est.map_points()


def covariance_ellipsoid(cov_enu: np.ndarray, k2: float = CHI2_3DOF_95) -> tuple[np.ndarray, np.ndarray]:
    """Orientation (quaternion w-first) and full axis lengths of the ``k2``-sigma² ellipsoid of a 3 × 3 covariance."""
    values, vectors = np.linalg.eigh(0.5 * (cov_enu + cov_enu.T))
    if np.linalg.det(vectors) < 0.0:
        vectors[:, 2] = -vectors[:, 2]
    return rot_to_quat(vectors), 2.0 * np.sqrt(k2 * np.clip(values, 0.0, None))


class FoxgloveScene:
    """The view's channels on one foxglove-sdk context, fed on the runtime's loop."""

    def __init__(self, context: foxglove.Context, origin: Callable[[], Origin], rate_hz: float, path_points: int) -> None:
        c = dict(context=context)
        self.tf = ch.FrameTransformsChannel("/tf", **c)
        self.pose_channel = ch.PoseInFrameChannel("/pose", **c)
        self.path_channel = ch.PosesInFrameChannel("/path", **c)
        self.covariance = ch.SceneUpdateChannel("/covariance", **c)
        self.gps_fix = ch.LocationFixChannel("/gps", **c)
        self.gps_local = ch.SceneUpdateChannel("/gps/local", **c)
        self.landmark_channel = ch.SceneUpdateChannel("/landmarks", **c)
        self.image = ch.CompressedImageChannel("/camera/image", **c)
        self.overlay = ch.ImageAnnotationsChannel("/camera/overlay", **c)
        self.status_channel = foxglove.Channel("/status", context=context)
        self.origin = origin
        self.period_ns = int(1e9 / rate_hz)
        self._next_pose_ns: int | None = None
        self._next_path_ns: int | None = None
        self._path: deque[Pose] = deque(maxlen=path_points)
        self._gps: deque[np.ndarray] = deque(maxlen=GPS_SHOWN)  # ENU
        self.last_t_ns = 0
        self.counts = {"poses": 0, "gps": 0, "frames": 0, "status": 0}

    # ------------------------------------------------------------------------- estimates
    def pose(self, pose: OutputPose) -> None:
        """Pose, TF, covariance at ``rate_hz``, path at 2 Hz (sensor time)."""
        t = pose.t_ns
        self.last_t_ns = t
        if not pose.position_initialized or (self._next_pose_ns is not None and t < self._next_pose_ns):
            return
        self._next_pose_ns = t + self.period_ns
        p_enu, q_enu = pose_ned_frd_to_enu_flu(pose.p, pose.q)
        ts, here = stamp(t), Pose(position=_vec(p_enu), orientation=_quat(q_enu))
        self.tf.log(FrameTransforms(transforms=[FrameTransform(
            timestamp=ts, parent_frame_id="map", child_frame_id="base_link", translation=_vec(p_enu),
            rotation=_quat(q_enu))]), log_time=t)
        self.pose_channel.log(PoseInFrame(timestamp=ts, frame_id="map", pose=here), log_time=t)
        cov_enu = R_ENU_NED @ pose.pose_cov[0:3, 0:3] @ R_ENU_NED.T
        if np.all(np.isfinite(cov_enu)):
            q_axes, size = covariance_ellipsoid(cov_enu)
            self.covariance.log(SceneUpdate(entities=[SceneEntity(
                timestamp=ts, frame_id="map", id="position_95",
                spheres=[SpherePrimitive(pose=Pose(position=_vec(p_enu), orientation=_quat(q_axes)), size=_vec(size),
                                         color=Color(r=1.0, g=0.4, b=0.0, a=0.35))])]), log_time=t)
        self._path.append(here)
        if self._next_path_ns is None or t >= self._next_path_ns:
            self._next_path_ns = t + PATH_PERIOD_NS
            self.path_channel.log(PosesInFrame(timestamp=ts, frame_id="map", poses=list(self._path)), log_time=t)
        self.counts["poses"] += 1

    def status(self, doc: dict[str, Any]) -> None:
        t = doc.get("t_ns") or self.last_t_ns
        self.status_channel.log(doc, log_time=int(t))
        self.counts["status"] += 1

    # ----------------------------------------------------------------------------- sensors
    def gps(self, fix: GpsFix) -> None:
        """A fix as latitude/longitude (around the NED origin, once there is one) and as a point in ``map``."""
        t, ts = fix.t_ns, stamp(fix.t_ns)
        origin = self.origin()
        if origin is not None:
            lat, lon, alt = pymap3d.ned2geodetic(*fix.p_ned, *origin)
            self.gps_fix.log(LocationFix(
                timestamp=ts, frame_id="gps", latitude=float(lat), longitude=float(lon), altitude=float(alt),
                position_covariance=np.diag([fix.sigma_h**2, fix.sigma_h**2, fix.sigma_v**2]).reshape(9).tolist(),
                position_covariance_type=LocationFixPositionCovarianceType.DiagonalKnown), log_time=t)
        self._gps.append(ned_to_enu(fix.p_ned))
        size = _vec(np.full(3, 0.3))
        self.gps_local.log(SceneUpdate(entities=[SceneEntity(
            timestamp=ts, frame_id="map", id="gps_fixes",
            spheres=[SpherePrimitive(pose=Pose(position=_vec(p), orientation=Quaternion(w=1.0)), size=size, color=CYAN)
                     for p in self._gps])]), log_time=t)
        self.counts["gps"] += 1

    def frame(self, image: np.ndarray | None, features: FrameFeatures, report: FrameReport,
              landmarks_ned: np.ndarray | None) -> None:
        """The camera picture (JPEG), its overlay, and the landmark map after this frame (if given)."""
        t, ts = report.t_ns, stamp(report.t_ns)
        if image is not None:  # at the features' frame size: the overlay's pixels are those
            ok, jpeg = cv2.imencode(".jpg", working_picture(image, features), [cv2.IMWRITE_JPEG_QUALITY, 85])
            if ok:
                self.image.log(CompressedImage(timestamp=ts, frame_id="camera", data=jpeg.tobytes(), format="jpeg"), log_time=t)
        self.overlay.log(overlay(features, report, ts), log_time=t)
        if landmarks_ned is not None:
            cube = _vec(np.full(3, 0.15))
            cubes = [CubePrimitive(pose=Pose(position=_vec(p), orientation=Quaternion(w=1.0)), size=cube, color=MAGENTA)
                     for p in ned_to_enu(landmarks_ned)]
            self.landmark_channel.log(SceneUpdate(entities=[SceneEntity(
                timestamp=ts, frame_id="map", id="landmarks", cubes=cubes)]), log_time=t)
        self.counts["frames"] += 1


def _p2(uv: np.ndarray) -> Point2:
    return Point2(x=float(uv[0]), y=float(uv[1]))


def overlay(features: FrameFeatures, report: FrameReport, ts: Timestamp) -> ImageAnnotations:
    """What the replay's ``--overlay`` pictures draw, as annotations Foxglove lays over the image."""
    keypoints = features.keypoints[:MAX_FEATURES_DRAWN]
    points = [PointsAnnotation(timestamp=ts, type=PointsAnnotationType.Points, points=[_p2(uv) for uv in keypoints],
                               outline_color=YELLOW, thickness=3.0)]
    predicted = {int(i): uv for i, uv in zip(report.predicted_ids, report.predicted_uv)}
    circles = [CircleAnnotation(timestamp=ts, position=_p2(uv), diameter=2.0 * float(report.gate_px), thickness=1.0,
                                outline_color=CYAN) for uv in predicted.values()]
    pairs = [q for i, f in zip(report.matched_ids, report.matched_features) if int(i) in predicted
             for q in (_p2(predicted[int(i)]), _p2(features.keypoints[f]))]
    if pairs:
        points.append(PointsAnnotation(timestamp=ts, type=PointsAnnotationType.LineList, points=pairs,
                                       outline_color=GREEN, thickness=2.0))
    if len(report.new_features):
        points.append(PointsAnnotation(timestamp=ts, type=PointsAnnotationType.Points, outline_color=MAGENTA, thickness=6.0,
                                       points=[_p2(features.keypoints[f]) for f in report.new_features]))
    if report.accepted:
        text, colour = (f"features {report.n_features}  in view {report.candidates}  matched {report.n_matches}  "
                        f"new {len(report.new_ids)}  map {report.n_landmarks}"), WHITE
    else:
        text, colour = f"REJECTED: {report.reason}", RED
    return ImageAnnotations(timestamp=ts, circles=circles, points=points, texts=[TextAnnotation(
        timestamp=ts, position=Point2(x=6.0, y=16.0), text=text, font_size=14.0, text_color=colour,
        background_color=Color(r=0.0, g=0.0, b=0.0, a=0.6))])


class FoxgloveOutput:
    """The scene served over WebSocket (foxglove-sdk), listening on ``host:port`` only (port 0: any free one)."""

    name = "foxglove"

    def __init__(self, host: str, port: int, rate_hz: float, path_points: int,
                 origin: Callable[[], Origin] = lambda: None, landmarks: Landmarks | None = None) -> None:
        self.host, self.port = host, port
        self.landmarks = landmarks
        self.context = foxglove.Context()
        self.scene = FoxgloveScene(self.context, origin, rate_hz, path_points)
        self.worker = ViewWorker("foxglove-view")
        self.server: Any = None

    def open(self) -> None:
        self.server = foxglove.start_server(name="vtolpose", host=self.host, port=self.port, context=self.context)
        self.port = self.server.port
        self.worker.start()
        log.info("Foxglove live view: open ws://%s:%d in Foxglove", self.host, self.port)

    @property
    def stats(self) -> dict[str, Any]:
        return {"port": self.port, **self.scene.counts, **self.worker.stats}

    def publish(self, pose: OutputPose) -> None:
        self.worker.submit(self.scene.pose, pose)

    def publish_status(self, status: dict[str, Any]) -> None:
        self.worker.submit(self.scene.status, status)

    def on_sample(self, sample: Any) -> None:
        if isinstance(sample, GpsFix):
            self.worker.submit(self.scene.gps, sample)

    def on_frame(self, image: np.ndarray | None, features: FrameFeatures, report: FrameReport) -> None:
        points = self.landmarks()[1] if self.landmarks is not None else None  # read here, on the filter's loop
        self.worker.submit(self.scene.frame, image, features, report, points)

    async def serve(self, stop: asyncio.Event) -> None:
        await stop.wait()

    def close(self) -> None:
        self.worker.stop()
        if self.server is not None:
            self.server.stop()
            self.server = None
