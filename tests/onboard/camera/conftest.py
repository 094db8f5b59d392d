"""Fixtures of the camera tests: GStreamer (skipped with the reason where absent), a loopback RTSP server, a
calibration file (the pair of Zenoh sessions, ``bus_pair``, is in tests/conftest.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.helpers.ports import free_tcp_port
from tests.onboard.camera.support import write_calibration


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
def calibration(tmp_path) -> Path:
    return write_calibration(tmp_path / "camera.toml")
