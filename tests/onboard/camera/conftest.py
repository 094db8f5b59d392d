"""Fixtures of the camera tests: GStreamer (skipped with the reason where absent), a loopback RTSP server, a
pair of Zenoh sessions on loopback, a calibration file."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.helpers.ports import free_tcp_port

#: a live 30 fps 320x240 test pattern
TEST_PIPELINE = "videotestsrc is-live=true pattern=ball ! video/x-raw,width=320,height=240,framerate=30/1"


@pytest.fixture()
def gst():
    """(Gst, GLib), or skip: the GStreamer sources need PyGObject and GStreamer."""
    pytest.importorskip("gi", reason="PyGObject (gi) not installed: scripts/setup-system.sh then pip install -e .[camera]")
    from onboard.camera.errors import CameraSourceError
    from onboard.camera.gst import require_gst

    try:
        return require_gst()
    except CameraSourceError as e:
        pytest.skip(str(e))


@pytest.fixture()
def rtsp_server(gst):
    """A started :class:`LoopbackRtspServer` (stopped after the test)."""
    try:
        import gi

        gi.require_version("GstRtspServer", "1.0")
    except ValueError as e:
        pytest.skip(f"GstRtspServer typelib missing (apt-get install gir1.2-gst-rtsp-server-1.0): {e}")
    from tests.onboard.camera.rtsp_server import LoopbackRtspServer

    servers: list[LoopbackRtspServer] = []

    def make(port: int | None = None) -> LoopbackRtspServer:
        s = LoopbackRtspServer(port or free_tcp_port()).start()
        servers.append(s)
        return s

    yield make
    for s in servers:
        s.stop()


@pytest.fixture()
def bus_pair():
    """Two Zenoh sessions on loopback (rendezvous a, peer b)."""
    from comms.transport import Transport, TransportConfig

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    a = Transport.open(TransportConfig.rendezvous(ep), "a")
    b = Transport.open(TransportConfig.local_peer(ep), "b")
    yield a, b
    b.close()
    a.close()


def write_calibration(path: Path, width_px: int = 320, height_px: int = 240, *, distortion: bool = True) -> Path:
    dist = "distortion_model = \"plumb_bob\"\ndistortion = [-0.1, 0.01, 0.0, 0.0, 0.0]\n" if distortion else ""
    path.write_text(f"[camera]\nwidth_px = {width_px}\nheight_px = {height_px}\nfx_px = 300.0\nfy_px = 300.0\n"
                    f"cx_px = {width_px / 2 - 0.5}\ncy_px = {height_px / 2 - 0.5}\n{dist}"
                    "\n[calibration]\nboard = \"charuco\"\n")
    return path


@pytest.fixture()
def calibration(tmp_path) -> Path:
    return write_calibration(tmp_path / "camera.toml")
