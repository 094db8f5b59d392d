"""Capture sources: GStreamer (live test pattern), RTSP on loopback, file and image-folder replay, the
simulator's topic, and the errors a user meets."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from onboard.camera.config import CameraConfig
from onboard.camera.errors import CameraSourceError
from onboard.camera.sources import (FileSource, GStreamerSource, RtspSource, SimSource, V4L2Source, open_source,
                                    parse_source)
from tests.onboard.camera.support import TEST_PIPELINE


def read_for(src, seconds: float, max_frames: int = 10_000) -> list:
    frames, t0 = [], time.monotonic()
    while time.monotonic() - t0 < seconds and len(frames) < max_frames:
        f = src.read(0.5)
        if f is not None:
            frames.append(f)
        elif src.ended:
            break
    return frames


def test_parse_source_forms(tmp_path) -> None:
    assert parse_source("v4l2:/dev/video0") == ("v4l2", "/dev/video0")
    assert parse_source("/dev/video2") == ("v4l2", "/dev/video2")
    assert parse_source("gst:videotestsrc ! videoconvert") == ("gstreamer", "videotestsrc ! videoconvert")
    assert parse_source("gstreamer:videotestsrc") == ("gstreamer", "videotestsrc")
    assert parse_source("rtsp://10.0.0.5:8554/cam") == ("rtsp", "rtsp://10.0.0.5:8554/cam")
    assert parse_source("sim:drone_2") == ("sim", "drone_2")
    assert parse_source(f"file:{tmp_path}/x.mp4") == ("file", f"{tmp_path}/x.mp4")
    assert parse_source(str(tmp_path)) == ("file", str(tmp_path))
    with pytest.raises(CameraSourceError, match="not understood.*v4l2:/dev/video0"):
        parse_source("webcam")
    with pytest.raises(CameraSourceError, match="nothing after"):
        parse_source("gst:")


def test_missing_v4l2_device_names_it_and_how_to_list(gst) -> None:
    src = V4L2Source("/dev/video97")
    with pytest.raises(CameraSourceError, match=r"/dev/video97 not found.*v4l2-ctl --list-devices"):
        src.open()
    assert "v4l2-ctl" in src.stats.last_error
    assert "v4l2src device=/dev/video97" in src.pipeline_description()
    sized = V4L2Source("/dev/video0", size=(1280, 720), rate_hz=30).pipeline_description()
    assert "video/x-raw,width=1280,height=720,framerate=30/1;image/jpeg,width=1280" in sized


def test_bad_pipeline_is_a_clear_error(gst) -> None:
    with pytest.raises(CameraSourceError, match=r"bad GStreamer pipeline \(no element \"nosuchsrc\"\).*gst-launch-1.0"):
        GStreamerSource("nosuchsrc ! videoconvert").open()
    with pytest.raises(CameraSourceError, match="empty pipeline"):
        GStreamerSource(" ! ")


def test_gstreamer_live_pattern_times_and_intervals(gst) -> None:
    src = open_source(CameraConfig(source="gstreamer", uri=TEST_PIPELINE))
    try:
        frames = read_for(src, 1.5)
    finally:
        src.close()
    assert len(frames) >= 30, len(frames)
    assert frames[0].image.shape == (240, 320, 3) and frames[0].image.dtype == np.uint8
    t = np.array([f.t_capture_ns for f in frames])
    assert (np.diff(t) > 0).all(), "capture times must increase strictly"
    assert np.median(np.diff(t)) / 1e6 == pytest.approx(33.3, abs=2.0)
    latency_ms = np.array([f.t_received_ns - f.t_capture_ns for f in frames]) / 1e6
    # model: PTS = the clock time videotestsrc made the frame; received right after (no sink sync)
    assert (latency_ms > -1.0).all() and np.median(latency_ms) < 20.0 and latency_ms.max() < 100.0, latency_ms
    assert abs(frames[-1].t_capture_ns - time.time_ns()) < 1e9  # realtime clock
    idx = [f.frame_index for f in frames]
    assert idx == list(range(idx[0], idx[0] + len(idx))) and src.stats.dropped == 0
    assert src.describe().startswith("gstreamer:videotestsrc")


def test_gstreamer_pipeline_eos_ends_the_source(gst) -> None:
    src = GStreamerSource("videotestsrc is-live=true num-buffers=5 ! video/x-raw,width=64,height=48,framerate=30/1")
    src.open()
    frames = read_for(src, 3.0)
    assert len(frames) == 5 and src.ended
    assert src.read(0.1) is None
    src.close()
    # a producer faster than the reader: the appsink keeps the newest, the offset gaps count the rest
    src = GStreamerSource("videotestsrc num-buffers=50 ! video/x-raw,width=64,height=48")
    src.open()
    time.sleep(0.3)
    frames = read_for(src, 3.0)
    assert src.ended and 1 <= len(frames) < 50 and len(frames) + src.stats.dropped == 50
    src.close()


def test_gstreamer_scales_to_the_configured_size(gst) -> None:
    with open_source(CameraConfig(source="gstreamer", uri=TEST_PIPELINE, width_px=160, height_px=120)) as src:
        f = read_for(src, 2.0, max_frames=1)[0]
    assert f.image.shape == (120, 160, 3)


def test_rtsp_stream_on_loopback(rtsp_server) -> None:
    server = rtsp_server()
    src = RtspSource(server.url, latency_s=0.005)
    src.open()
    try:
        frames = read_for(src, 2.5)
    finally:
        src.close()
    assert len(frames) >= 40, len(frames)
    assert frames[0].image.shape == (240, 320, 3)
    t = np.array([f.t_capture_ns for f in frames])
    assert (np.diff(t) > 0).all()
    assert np.median(np.diff(t)) / 1e6 == pytest.approx(33.3, abs=3.0)
    latency_ms = np.array([f.t_received_ns - f.t_capture_ns for f in frames]) / 1e6
    # model: arrival (jitterbuffer PTS) - latency_s, or the sender's NTP time: decode + jitterbuffer < 150 ms
    assert np.median(latency_ms) < 150.0 and (latency_ms > -5.0).all(), latency_ms
    assert src.stats.dropped <= 2
    assert "jitterbuffer" in src.latency_model


def write_video(path, n: int = 12, fps: float = 20.0, size=(320, 240)) -> None:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, size)
    assert w.isOpened()
    for i in range(n):
        img = np.full((size[1], size[0], 3), 10 * i, np.uint8)
        cv2.putText(img, str(i), (20, 100), cv2.FONT_HERSHEY_SIMPLEX, 2, (255, 255, 255), 3)
        w.write(img)
    w.release()


def test_file_video_replays_in_real_time_then_ends(tmp_path) -> None:
    path = tmp_path / "clip.avi"
    write_video(path, n=12, fps=20.0)
    src = open_source(CameraConfig(source="file", uri=str(path), latency_s=0.05))
    assert src.rate_hz == pytest.approx(20.0)
    t0 = time.monotonic()
    frames = read_for(src, 5.0)
    elapsed = time.monotonic() - t0
    assert [f.frame_index for f in frames] == list(range(12)) and src.ended and src.read(0.1) is None
    assert elapsed == pytest.approx(11 / 20.0, abs=0.25)
    assert all(f.t_received_ns - f.t_capture_ns == 50_000_000 for f in frames)
    assert frames[3].image.shape == (240, 320, 3) and abs(int(frames[3].image[5, 5, 0]) - 30) <= 6
    src.close()


def test_file_slow_reader_drops_and_loop_restarts(tmp_path) -> None:
    path = tmp_path / "clip.avi"
    write_video(path, n=10, fps=50.0, size=(64, 48))
    src = FileSource(path, loop=True)
    src.open()
    src.read(1.0)
    time.sleep(0.1)  # 5 frame periods: the replay skips what a live camera would have overwritten
    f = src.read(1.0)
    assert f.frame_index >= 5 and src.stats.dropped == f.frame_index - 1
    frames = read_for(src, 1.0, max_frames=8)
    assert 0 in [g.frame_index for g in frames] and not src.ended  # looped
    src.close()


def test_image_folder_natural_order(tmp_path) -> None:
    for i in (1, 2, 10):
        cv2.imwrite(str(tmp_path / f"img{i}.png"), np.full((48, 64, 3), i * 20, np.uint8))
    (tmp_path / "notes.txt").write_text("not an image")
    src = FileSource(tmp_path, rate_hz=100.0)
    src.open()
    frames = read_for(src, 2.0)
    assert [int(f.image[0, 0, 0]) for f in frames] == [20, 40, 200] and src.ended
    src.close()


def test_file_errors(tmp_path) -> None:
    with pytest.raises(CameraSourceError, match="does not exist"):
        FileSource(tmp_path / "nope.mp4").open()
    with pytest.raises(CameraSourceError, match="holds no images"):
        FileSource(tmp_path).open()
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"not a video")
    with pytest.raises(CameraSourceError, match="cannot read"):
        FileSource(bad).open()


def test_sim_source_reads_the_simulators_topic(bus_pair) -> None:
    from shared_msgs import keys
    from shared_msgs.messages import CameraFrame

    a, b = bus_pair
    src = SimSource("drone_1", fleet="f1", bus=b)
    src.open()
    time.sleep(0.5)
    key = keys.drone_key("f1", "drone_1", keys.CAMERA_IMAGE)
    img = np.full((48, 64, 3), 128, np.uint8)
    data = cv2.imencode(".jpg", img)[1].tobytes()
    frames = []
    for i in (0, 1, 3):
        a.publish(key, CameraFrame(header=CameraFrame.make_header("drone_1", 1_000_000_000 + i, i), camera_id="cam0",
                                   frame_index=i, encoding="jpeg", width_px=64, height_px=48, data=data))
        frames += read_for(src, 2.0, max_frames=1)
    assert [f.frame_index for f in frames] == [0, 1, 3] and src.stats.dropped == 1  # the gap
    for i in range(4, 8):  # a reader that does not keep up: the oldest are overwritten, and counted
        a.publish(key, CameraFrame(header=CameraFrame.make_header("drone_1", 1_000_000_000 + i, i), camera_id="cam0",
                                   frame_index=i, encoding="jpeg", width_px=64, height_px=48, data=data))
    time.sleep(0.3)
    frames += read_for(src, 0.5)
    src.close()
    assert [f.frame_index for f in frames][3:] == [6, 7] and src.stats.dropped == 3
    assert frames[2].t_capture_ns == 1_000_000_003 and frames[0].image.shape == (48, 64, 3)
    assert src.describe() == "sim:drone_1"


def test_without_pygobject_the_error_names_the_fix(monkeypatch) -> None:
    import sys

    import onboard.camera.gst as gst_mod

    monkeypatch.setattr(gst_mod, "_gst", None)
    monkeypatch.setitem(sys.modules, "gi", None)  # as on a base install without the 'camera' extra
    with pytest.raises(CameraSourceError, match=r"scripts/setup-system.sh then pip install -e \.\[camera\]"):
        GStreamerSource("videotestsrc").open()
