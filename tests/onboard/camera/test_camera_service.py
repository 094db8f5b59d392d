"""The camera service over a real Zenoh session on loopback: frames, thumbnails, CameraInfo, CameraStatus,
a source that disappears and comes back, and the errors of a bad calibration."""

from __future__ import annotations

import threading
import time

import pytest

from onboard.camera.config import CameraConfig
from onboard.camera.service import CameraService, scale_camera
from shared_msgs import keys
from shared_msgs.messages import CameraFrame, CameraInfo, CameraStatus
from skycap.camera import CameraError, PinholeCamera
from skycap.config import ConfigError
from tests.onboard.camera.support import TEST_PIPELINE, write_calibration


class Inbox:
    """Everything b receives on drone_1's camera topics."""

    def __init__(self, bus, fleet: str = "f1", drone: str = "drone_1") -> None:
        self.lock = threading.Lock()
        self.got: dict[str, list] = {t: [] for t in (keys.CAMERA_IMAGE, keys.CAMERA_THUMB, keys.CAMERA_INFO,
                                                     keys.CAMERA_STATUS)}
        for topic, cls in ((keys.CAMERA_IMAGE, CameraFrame), (keys.CAMERA_THUMB, CameraFrame),
                           (keys.CAMERA_INFO, CameraInfo), (keys.CAMERA_STATUS, CameraStatus)):
            bus.subscribe(keys.drone_key(fleet, drone, topic), self._put(topic), cls)

    def _put(self, topic: str):
        def cb(rx) -> None:
            with self.lock:
                self.got[topic].append(rx)
        return cb

    def msgs(self, topic: str) -> list:
        with self.lock:
            return [rx.msg for rx in self.got[topic]]

    def wait(self, cond, timeout_s: float) -> bool:
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s:
            if cond(self):
                return True
            time.sleep(0.05)
        return cond(self)


def cam_cfg(calibration, **kw) -> CameraConfig:
    base = dict(source="gstreamer", uri=TEST_PIPELINE, calibration_file=str(calibration), thumbnail_hz=2.0,
                thumbnail_width_px=160, jpeg_quality=80, reconnect_after_s=1.0)
    base.update(kw)
    return CameraConfig(**base).validate()


def test_service_publishes_frames_thumbs_info_status(gst, bus_pair, calibration) -> None:
    a, b = bus_pair
    inbox = Inbox(b)
    time.sleep(0.3)
    svc = CameraService(cam_cfg(calibration), a, "f1", "drone_1").start()
    try:
        assert inbox.wait(lambda i: len(i.msgs(keys.CAMERA_STATUS)) >= 2 and len(i.msgs(keys.CAMERA_THUMB)) >= 3,
                          8.0)
    finally:
        svc.stop()
    assert inbox.wait(lambda i: i.msgs(keys.CAMERA_STATUS)[-1].detail == "stopped", 3.0)  # the last word
    frames = inbox.msgs(keys.CAMERA_IMAGE)
    assert len(frames) >= 20
    f = frames[-1]
    assert (f.width_px, f.height_px, f.encoding, f.camera_id) == (320, 240, "jpeg", "cam0")
    assert f.source.startswith("gstreamer:videotestsrc") and f.header.sender_id == "drone_1"
    t = [m.header.t_measurement_ns for m in frames]
    assert all(x < y for x, y in zip(t, t[1:]))
    idx = [m.frame_index for m in frames]
    assert idx == sorted(idx)
    rx = inbox.got[keys.CAMERA_IMAGE][-1]
    assert 0 <= rx.t_received_ns - f.header.t_measurement_ns < 200e6  # capture -> another process's receive
    thumbs = inbox.msgs(keys.CAMERA_THUMB)
    assert (thumbs[0].width_px, thumbs[0].height_px) == (160, 120) and len(thumbs) <= len(frames) // 5
    info = inbox.msgs(keys.CAMERA_INFO)[-1]
    assert (info.width_px, info.height_px, info.fx_px, info.distortion_model) == (320, 240, 300.0, "plumb_bob")
    assert info.distortion == (-0.1, 0.01, 0.0, 0.0, 0.0)
    statuses = inbox.msgs(keys.CAMERA_STATUS)
    live = [s for s in statuses if s.connected]
    assert live and live[-1].frames >= 10 and live[-1].dropped == 0 and live[-1].rate_hz == pytest.approx(30, abs=8)
    assert live[-1].detail == "" and live[-1].source.startswith("gstreamer:")
    assert statuses[-1].connected is False and statuses[-1].detail == "stopped"


def test_source_that_ends_is_reported_and_reopened(gst, bus_pair, calibration) -> None:
    a, b = bus_pair
    inbox = Inbox(b)
    time.sleep(0.3)
    short = "videotestsrc is-live=true num-buffers=10 ! video/x-raw,width=320,height=240,framerate=30/1"
    svc = CameraService(cam_cfg(calibration, uri=short), a, "f1", "drone_1").start()
    try:
        assert inbox.wait(lambda i: svc.counters.reconnects >= 1 and len(i.msgs(keys.CAMERA_IMAGE)) >= 15, 8.0)
    finally:
        svc.stop()
    down = [s for s in inbox.msgs(keys.CAMERA_STATUS) if not s.connected and "the stream ended" in s.detail]
    assert down, [s.detail for s in inbox.msgs(keys.CAMERA_STATUS)]
    assert any(s.connected and s.reconnects >= 1 for s in inbox.msgs(keys.CAMERA_STATUS))


def lost_after_connected(statuses: list) -> list:
    first = next((k for k, s in enumerate(statuses) if s.connected), None)
    return [] if first is None else [s for s in statuses[first:] if not s.connected]


def test_rtsp_camera_lost_then_back(rtsp_server, bus_pair, calibration) -> None:
    a, b = bus_pair
    server = rtsp_server()
    inbox = Inbox(b)
    time.sleep(0.3)
    svc = CameraService(cam_cfg(calibration, source="rtsp", uri=server.url), a, "f1", "drone_1").start()
    try:
        assert inbox.wait(lambda i: len(i.msgs(keys.CAMERA_IMAGE)) >= 10, 8.0)
        server.stop()
        assert inbox.wait(lambda i: lost_after_connected(i.msgs(keys.CAMERA_STATUS)), 5.0)
        n_down = len(inbox.msgs(keys.CAMERA_IMAGE))
        rtsp_server(server.port)  # the camera is back on the same address
        assert inbox.wait(lambda i: len(i.msgs(keys.CAMERA_IMAGE)) >= n_down + 10 and svc.connected, 12.0)
    finally:
        svc.stop()
    lost = lost_after_connected(inbox.msgs(keys.CAMERA_STATUS))
    assert lost and lost[0].detail != "stopped" and "Could not" in lost[0].detail, lost[0]
    assert svc.counters.reconnects >= 1
    assert any(s.connected and s.reconnects >= 1 for s in inbox.msgs(keys.CAMERA_STATUS))


def test_missing_calibration_and_sim_source_are_clear_errors(tmp_path, bus_pair) -> None:
    a, _ = bus_pair
    cfg = CameraConfig(source="file", uri=str(tmp_path), calibration_file=str(tmp_path / "nope.toml"))
    with pytest.raises(CameraError, match=r"nope.toml not found.*skycap camera calibrate"):
        CameraService(cfg, a, "f1", "drone_1").start()
    with pytest.raises(ConfigError, match="simulator's camera node"):
        CameraService(CameraConfig(), a, "f1", "drone_1")


def test_calibration_size_checked_against_frames(tmp_path, bus_pair) -> None:
    import cv2
    import numpy as np

    a, b = bus_pair
    inbox = Inbox(b)
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), np.zeros((240, 320, 3), np.uint8))
    # same aspect ratio, half the size: intrinsics scaled
    half = write_calibration(tmp_path / "half.toml", 640, 480)
    svc = CameraService(CameraConfig(source="file", uri=str(tmp_path), rate_hz=30.0, calibration_file=str(half)),
                        a, "f1", "drone_1").start()
    try:
        assert inbox.wait(lambda i: any(m.width_px == 320 for m in i.msgs(keys.CAMERA_INFO)), 5.0)
    finally:
        svc.stop()
    info = [m for m in inbox.msgs(keys.CAMERA_INFO) if m.width_px == 320][-1]
    assert info.fx_px == pytest.approx(150.0) and info.cx_px == pytest.approx(159.5)
    # another aspect ratio: no CameraInfo for these frames, the status says why
    wide = write_calibration(tmp_path / "wide.toml", 1280, 720)
    svc = CameraService(CameraConfig(source="file", uri=str(tmp_path), rate_hz=30.0, calibration_file=str(wide)),
                        a, "f1", "drone_1").start()
    try:
        assert inbox.wait(lambda i: any("aspect ratio" in s.detail for s in i.msgs(keys.CAMERA_STATUS)), 5.0)
    finally:
        svc.stop()
    assert svc.camera_info() is None
    cam = PinholeCamera.from_toml(wide)
    assert scale_camera(cam, 640, 360).fx_px == pytest.approx(150.0) and scale_camera(cam, 640, 480) is None


class FakeSource:
    """Delivers ``n`` frames (the 3rd one unencodable), then nothing (not ended: a camera gone silent);
    re-opening delivers again."""

    kind = "fake"
    latency_model = "fake"
    latency_s = 0.0

    def __init__(self, n: int = 6) -> None:
        from onboard.camera.sources import SourceStats

        self.n = n
        self.stats = SourceStats()
        self.left = 0
        self.ended = False
        self.i = 0

    def describe(self) -> str:
        return "fake:cam"

    def open(self) -> None:
        self.stats.opens += 1
        self.left = self.n

    def read(self, timeout_s: float = 1.0):
        import numpy as np

        from onboard.camera.frame import Frame

        if self.left <= 0:
            time.sleep(timeout_s)
            return None
        self.left -= 1
        self.i += 1
        time.sleep(0.01)
        img = np.zeros((240, 320, 3), np.uint8) if self.i != 3 else np.zeros((240, 320, 7), np.uint8)
        return Frame(image=img, t_capture_ns=time.time_ns(), frame_index=self.i, t_received_ns=time.time_ns())

    def close(self) -> None:
        pass


def test_silent_camera_reported_reopened_and_bad_frame_skipped(bus_pair, calibration) -> None:
    a, b = bus_pair
    inbox = Inbox(b)
    time.sleep(0.3)
    src = FakeSource()
    cfg = CameraConfig(source="v4l2", uri="/dev/video0", calibration_file=str(calibration), reconnect_after_s=0.4)
    svc = CameraService(cfg, a, "f1", "drone_1", source=src).start()
    try:
        assert inbox.wait(lambda i: svc.counters.reconnects >= 1 and svc.counters.frames >= 7, 6.0)
    finally:
        svc.stop()
    assert svc.counters.bad_frames >= 1 and src.stats.opens >= 2
    lost = lost_after_connected(inbox.msgs(keys.CAMERA_STATUS))
    assert lost and "fake:cam: no frame for" in lost[0].detail, lost
