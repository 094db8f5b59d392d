"""An RTSP server on loopback for the camera tests (GstRtspServer, its own GLib main loop thread)."""

from __future__ import annotations

import threading
import time

LAUNCH = ("( videotestsrc is-live=true pattern=ball ! video/x-raw,width={w},height={h},framerate={fps}/1 ! "
          "x264enc tune=zerolatency speed-preset=ultrafast key-int-max={fps} bitrate=500 ! "
          "rtph264pay name=pay0 pt=96 config-interval=1 )")


class LoopbackRtspServer:
    """``rtsp://127.0.0.1:<port>/cam`` serving a live 320x240 H.264 test pattern; ``start()`` / ``stop()``
    (stop closes the listening socket and drops every client, as a camera that is switched off)."""

    def __init__(self, port: int, *, width: int = 320, height: int = 240, fps: int = 30) -> None:
        import gi

        gi.require_version("Gst", "1.0")
        gi.require_version("GstRtspServer", "1.0")
        from gi.repository import GLib, Gst, GstRtspServer

        Gst.init(None)
        self.GLib, self.GstRtspServer = GLib, GstRtspServer
        self.port = port
        self.launch = LAUNCH.format(w=width, h=height, fps=fps)
        self.url = f"rtsp://127.0.0.1:{port}/cam"
        self._ctx = None
        self._loop = None
        self._thread: threading.Thread | None = None
        self._server = None
        self._source_id = None

    def start(self) -> "LoopbackRtspServer":
        GLib, R = self.GLib, self.GstRtspServer
        self._ctx = GLib.MainContext.new()
        self._loop = GLib.MainLoop.new(self._ctx, False)
        server = R.RTSPServer.new()
        server.set_address("127.0.0.1")
        server.set_service(str(self.port))
        factory = R.RTSPMediaFactory.new()
        factory.set_launch(self.launch)
        factory.set_shared(True)
        server.get_mount_points().add_factory("/cam", factory)
        self._source_id = server.attach(self._ctx)
        if not self._source_id:
            raise RuntimeError(f"RTSP server cannot listen on 127.0.0.1:{self.port}")
        self._server = server
        self._thread = threading.Thread(target=self._loop.run, name="rtsp-server", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        if self._server is None:
            return
        R = self.GstRtspServer
        done = threading.Event()

        def shutdown() -> bool:
            self._server.client_filter(lambda *_: R.RTSPFilterResult.REMOVE)
            src = self._ctx.find_source_by_id(self._source_id)
            if src is not None:
                src.destroy()
            done.set()
            return False

        self._ctx.invoke_full(self.GLib.PRIORITY_DEFAULT, shutdown)
        done.wait(5.0)
        time.sleep(0.2)  # let the sessions' pipelines wind down
        self._loop.quit()
        if self._thread is not None:
            self._thread.join(5.0)
        self._server = None
        self._thread = None
