"""Camera drivers: OpenCV against a real video file; libdc1394 binding loads and reports no camera."""

from __future__ import annotations

import ctypes.util

import cv2
import numpy as np
import pytest

import vtolpose.drivers.camera.dc1394 as dc
from vtolpose.config import load_config
from vtolpose.config.sections import build_sections
from vtolpose.drivers.camera.common import CameraUnavailable
from vtolpose.drivers.camera.select import camera_from_config
from vtolpose.drivers.camera.opencv import OpenCvCamera, OpenCvCameraConfig

N_FRAMES, W, H = 12, 160, 120


@pytest.fixture
def video(tmp_path):
    """An MJPG .avi whose frames get brighter one step at a time, with a moving bar."""
    path = tmp_path / "flight.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 7.5, (W, H))
    assert writer.isOpened(), "OpenCV cannot write MJPG on this machine"
    for k in range(N_FRAMES):
        image = np.full((H, W, 3), 40 + 15 * k, dtype=np.uint8)
        image[:, 10 * k:10 * k + 8] = 255
        writer.write(image)
    writer.release()
    return path


def test_opencv_video_file_gives_grey_frames_in_order(video):
    camera = OpenCvCamera(OpenCvCameraConfig(str(video), latency_s=0.02))
    assert "160 x 120" in camera.open()
    frames = []
    while (frame := camera.read()) is not None:
        frames.append(frame)
    camera.close()
    assert len(frames) == N_FRAMES and camera.ended
    assert [f.seq for f in frames] == list(range(1, N_FRAMES + 1))
    assert all(f.image.shape == (H, W) and f.image.dtype == np.uint8 for f in frames)
    means = [float(np.median(f.image)) for f in frames]
    assert means == pytest.approx([40 + 15 * k for k in range(N_FRAMES)], abs=4)  # JPEG is lossy
    assert all(b.t_ns > a.t_ns for a, b in zip(frames, frames[1:]))
    assert camera.read() is None


def test_opencv_missing_source_and_type_none_say_so(tmp_path):
    with pytest.raises(CameraUnavailable, match="could not open"):
        OpenCvCamera(OpenCvCameraConfig(str(tmp_path / "nothing.avi"))).open()
    camera = build_sections(load_config(overrides={"sensors": {"camera": {"type": "none"}}})).sensors.camera
    with pytest.raises(CameraUnavailable, match="no camera configured"):
        camera_from_config(camera)
    opencv = camera_from_config(camera, kind="opencv", device="3")
    assert isinstance(opencv, OpenCvCamera) and opencv.config.source == 3


def test_format7_packet_size_sets_the_frame_rate():
    # 656 x 494 mono8 at 7.5 fps: 1066.7 packets per frame (one per 125 us cycle).
    assert dc.format7_packet_size(656, 494, 7.5, 4, 4096) == 304
    assert dc.format7_packet_size(656, 494, 7.5, 8, 4096) == 304
    assert dc.format7_packet_size(656, 494, 7.5, 4, 200) == 200  # capped at what the camera allows
    assert dc.VIDEO_MODES["format7_0"] == 88 and dc.VIDEO_MODES["640x480_mono8"] == 69


def test_libdc1394_binding_loads_and_reports_no_camera():
    try:
        dc.load_library()
    except CameraUnavailable as exc:
        pytest.skip(f"libdc1394 not installed here ({exc})")
    try:
        cameras = dc.list_cameras()
    except CameraUnavailable as exc:  # no FireWire/USB stack visible in this container
        assert "FireWire" in str(exc)
        return
    if cameras:
        pytest.skip(f"a real IIDC camera is attached: {cameras[0].describe()}")
    camera = dc.Dc1394Camera(dc.Dc1394Config())
    with pytest.raises(CameraUnavailable, match="no IIDC"):
        camera.open()
    camera.close()  # idempotent after a failed open
    assert camera.read(0.01) is None


def test_missing_libdc1394_gives_the_install_hint(monkeypatch):
    monkeypatch.setattr(dc, "_library", None)
    monkeypatch.setattr(dc, "_LIBRARY_NAMES", ("libdc1394-not-here.so.99",))
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None)
    with pytest.raises(CameraUnavailable, match="apt-get install libdc1394-25"):
        dc.load_library()
