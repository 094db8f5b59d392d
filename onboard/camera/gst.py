"""Thin adapter over GStreamer (PyGObject): a pipeline that ends in an appsink handing BGR frames with capture
times in the realtime clock.

    src = GstSource("videotestsrc is-live=true ! video/x-raw,width=320,height=240,framerate=30/1",
                    name="gstreamer:videotestsrc")
    src.open(); frame = src.read(1.0); src.close()

``gi`` is imported lazily (:func:`require_gst`): a drone's base install may lack it, and only the GStreamer
sources need it.

Time
----
A buffer's PTS is *running time*: the pipeline clock's time at that instant is ``base_time + pts``. Live
sources stamp buffers with the clock time of capture (v4l2src: the driver's capture timestamp, converted to the
pipeline clock; videotestsrc: the clock time it produced the buffer), so ``base_time + pts`` is the capture
instant in the pipeline clock. GStreamer's system clock is ``CLOCK_MONOTONIC``; rather than assume it, the
adapter samples ``(clock.get_time(), time.time_ns())`` together and keeps their offset (re-sampled every
:data:`CLOCK_OFFSET_REFRESH_S` to follow NTP slews of the realtime clock), so any pipeline clock works.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import numpy as np

from onboard.camera.errors import CameraSourceError
from onboard.camera.frame import Frame

log = logging.getLogger(__name__)

__all__ = ["require_gst", "GstSource", "CLOCK_OFFSET_REFRESH_S", "GST_INSTALL_HINT"]

GST_INSTALL_HINT = ("install GStreamer and the 'camera' extra: scripts/setup-system.sh then pip install -e .[camera]")
CLOCK_OFFSET_REFRESH_S = 10.0
#: the appsink keeps at most this many frames; older ones are dropped (and counted, from the index gaps)
APPSINK_MAX_BUFFERS = 2
_NTP_UNIX_OFFSET_NS = 2_208_988_800 * 1_000_000_000  # 1900-01-01 -> 1970-01-01

_gst: tuple[Any, Any] | None = None
_gst_lock = threading.Lock()


def _keep_gcc_unwinder() -> None:
    """Put libgcc_s's ``_Unwind_*`` in the process's global symbol scope before GStreamer brings libunwind there.

    libgstreamer links libunwind (for its debug backtraces), and PyGObject loads it with RTLD_GLOBAL. A C++
    library loaded or lazily bound afterwards (onnxruntime: every exception it throws, even one it catches itself)
    then resumes unwinding with libunwind's ``_Unwind_Resume`` on a frame libgcc's unwinder raised: abort. Seen
    here: the person detector opening a corrupt model file killed a process that had opened a camera. Loading
    libgcc_s globally first makes every later lookup find libgcc's unwinder."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("gcc_s") or "libgcc_s.so.1"
    try:
        ctypes.CDLL(name, mode=ctypes.RTLD_GLOBAL)
    except OSError as e:  # not glibc / no libgcc_s: nothing to protect
        log.debug("libgcc_s not loaded globally (%s)", e)


def require_gst() -> tuple[Any, Any]:
    """``(Gst, GLib)`` from PyGObject, initialised; a :class:`CameraSourceError` naming the fix when absent."""
    global _gst
    with _gst_lock:
        if _gst is None:
            _keep_gcc_unwinder()
            try:
                import gi

                gi.require_version("Gst", "1.0")
                gi.require_version("GstApp", "1.0")
                from gi.repository import GLib, Gst, GstApp  # noqa: F401  (GstApp: appsink's pull methods)
            except (ImportError, ValueError) as e:
                raise CameraSourceError(f"GStreamer camera sources need PyGObject and GStreamer 1.x ({e}); "
                                        f"{GST_INSTALL_HINT}") from None
            Gst.init(None)
            _gst = (Gst, GLib)
    return _gst


class _ClockMap:
    """Pipeline clock time -> realtime ns, by one offset sampled next to the clock and refreshed."""

    def __init__(self, clock: Any) -> None:
        self.clock = clock
        self.offset_ns = 0
        self._t_sampled = -1e18
        self.refresh()

    def refresh(self) -> None:
        # sample the realtime clock on both sides of the pipeline clock, keep the middle
        t0 = time.time_ns()
        c = self.clock.get_time()
        t1 = time.time_ns()
        self.offset_ns = (t0 + t1) // 2 - int(c)
        self._t_sampled = time.monotonic()

    def to_realtime_ns(self, clock_time_ns: int) -> int:
        if time.monotonic() - self._t_sampled > CLOCK_OFFSET_REFRESH_S:
            self.refresh()
        return int(clock_time_ns) + self.offset_ns


class GstSource:
    """A GStreamer pipeline description (without sink) + ``videoconvert ! BGR ! appsink``, as a frame source.

    ``name``: what :meth:`describe` says (e.g. "v4l2:/dev/video0"). ``latency_s``: subtracted from the capture
    time computed from the buffer's PTS (sources whose PTS is the arrival time, such as rtsp without RTCP
    sync); 0 for sources that stamp at capture. ``arrival_latency_s``: subtracted from the arrival time of a
    buffer without PTS. ``use_ntp_meta``: prefer a ``timestamp/x-ntp`` reference
    timestamp meta (rtspsrc ``add-reference-timestamp-meta``) when a buffer carries one: the sender's capture
    time once RTCP sender reports have arrived. ``size``: (width, height) to scale to (0 = keep).

    Not thread-safe: one reader thread. The stats live in ``self.stats`` (a :class:`SourceStats`) filled by the
    :class:`~onboard.camera.sources.FrameSource` wrapper that owns this adapter.
    """

    def __init__(self, description: str, *, name: str, latency_s: float = 0.0, arrival_latency_s: float = 0.0,
                 use_ntp_meta: bool = False, size: tuple[int, int] = (0, 0)) -> None:
        self.description = description
        self.name = name
        self.latency_s = float(latency_s)
        self.arrival_latency_s = float(arrival_latency_s)
        self.use_ntp_meta = use_ntp_meta
        self.size = size
        self.pipeline: Any = None
        self.sink: Any = None
        self.clock_map: _ClockMap | None = None
        self.ended = False
        self.error = ""
        self.ntp_frames = 0  #: frames timed by the sender's NTP reference meta
        self._ntp_caps: Any = None

    def full_description(self) -> str:
        w, h = self.size
        scale, size = "", ""
        if w > 0 and h > 0:
            scale, size = " ! videoscale", f",width={int(w)},height={int(h)}"
        return (f"{self.description} ! videoconvert{scale} ! video/x-raw,format=BGR{size} ! appsink name=skycap_sink "
                f"emit-signals=false sync=false drop=true max-buffers={APPSINK_MAX_BUFFERS}")

    def open(self, timeout_s: float = 5.0) -> None:
        Gst, GLib = require_gst()
        self.ended, self.error = False, ""
        desc = self.full_description()
        try:
            pipeline = Gst.parse_launch(desc)
        except GLib.Error as e:
            raise CameraSourceError(f"{self.name}: bad GStreamer pipeline ({e.message}): {desc!r}; try it with "
                                    f"gst-launch-1.0 {self.description} ! fakesink") from None
        self.pipeline = pipeline
        self.sink = pipeline.get_by_name("skycap_sink")
        if self.use_ntp_meta:
            self._ntp_caps = Gst.Caps.from_string("timestamp/x-ntp")
        ret = pipeline.set_state(Gst.State.PLAYING)
        if ret == Gst.StateChangeReturn.FAILURE:
            err = self._bus_error() or "the pipeline refused to start"
            self.close()
            raise CameraSourceError(f"{self.name}: cannot start the GStreamer pipeline: {err}")
        # live sources return NO_PREROLL; others preroll: wait (bounded) so that errors show here
        ret, _, _ = pipeline.get_state(int(timeout_s * Gst.SECOND))
        if ret == Gst.StateChangeReturn.FAILURE:
            err = self._bus_error() or "state change failed"
            self.close()
            raise CameraSourceError(f"{self.name}: cannot start the GStreamer pipeline: {err}")
        clock = pipeline.get_clock() or Gst.SystemClock.obtain()
        self.clock_map = _ClockMap(clock)

    def _bus_error(self) -> str:
        """Drain the bus: the first error's text (or ""); sets ``ended`` on EOS."""
        Gst, _ = require_gst()
        if self.pipeline is None:
            return ""
        bus = self.pipeline.get_bus()
        first = ""
        while True:
            msg = bus.pop_filtered(Gst.MessageType.ERROR | Gst.MessageType.EOS | Gst.MessageType.WARNING)
            if msg is None:
                return first
            if msg.type == Gst.MessageType.EOS:
                self.ended = True
            elif msg.type == Gst.MessageType.ERROR:
                err, dbg = msg.parse_error()
                text = f"{err.message} ({msg.src.get_name() if msg.src else '?'})"
                log.debug("%s: GStreamer error %s; %s", self.name, text, dbg)
                self.ended = True
                first = first or text
            else:
                w, _dbg = msg.parse_warning()
                log.warning("%s: GStreamer warning: %s", self.name, w.message)

    def pull(self, timeout_s: float) -> tuple[np.ndarray, int, int | None, int, int | None] | None:
        """Next frame: ``(image, t_capture_ns, source_index or None, t_received_ns, pts_ns or None)``, or None
        (timeout, EOS or error: then ``ended``/``error`` say which)."""
        Gst, _ = require_gst()
        if self.sink is None:
            return None
        sample = self.sink.try_pull_sample(int(max(0.0, timeout_s) * Gst.SECOND))
        t_received_ns = time.time_ns()
        if sample is None:
            err = self._bus_error()
            if err:
                self.error = err
            if self.sink.is_eos():
                self.ended = True
            return None
        buf = sample.get_buffer()
        s = sample.get_caps().get_structure(0)
        w, h = s.get_value("width"), s.get_value("height")
        ok, info = buf.map(Gst.MapFlags.READ)
        if not ok:
            return None
        try:
            data = np.frombuffer(info.data, dtype=np.uint8)
            stride = data.size // h if h else 0
            if stride < w * 3:
                raise CameraSourceError(f"{self.name}: buffer of {data.size} bytes is too small for {w}x{h} BGR")
            image = data[: stride * h].reshape(h, stride)[:, : w * 3].reshape(h, w, 3).copy()
        finally:
            buf.unmap(info)
        pts = buf.pts
        has_pts = pts != Gst.CLOCK_TIME_NONE
        if not has_pts or self.clock_map is None:  # no timestamp: arrival minus the latency model
            t_capture_ns = t_received_ns - int(self.arrival_latency_s * 1e9)
        else:
            t_capture_ns = self.clock_map.to_realtime_ns(self.pipeline.get_base_time() + pts)
            t_capture_ns -= int(self.latency_s * 1e9)
        if self._ntp_caps is not None:
            meta = buf.get_reference_timestamp_meta(self._ntp_caps)
            if meta is not None and meta.timestamp != Gst.CLOCK_TIME_NONE:
                t_ntp_ns = int(meta.timestamp) - _NTP_UNIX_OFFSET_NS
                self.ntp_frames += 1
                if self.ntp_frames == 1:
                    log.info("%s: RTCP sync: capture times now from the sender's NTP clock (%+.1f ms against the "
                             "arrival model)", self.name, (t_ntp_ns - t_capture_ns) / 1e6)
                t_capture_ns = t_ntp_ns
        off = buf.offset
        index = None if off == Gst.BUFFER_OFFSET_NONE else int(off)
        return image, int(t_capture_ns), index, t_received_ns, int(pts) if has_pts else None

    def framerate_hz(self) -> float:
        """The negotiated frame rate of the appsink's caps (0 when unknown or variable)."""
        if self.sink is None:
            return 0.0
        pad = self.sink.get_static_pad("sink")
        caps = pad.get_current_caps() if pad is not None else None
        if caps is None or caps.get_size() == 0:
            return 0.0
        ok, num, den = caps.get_structure(0).get_fraction("framerate")
        return float(num) / float(den) if ok and den and num else 0.0

    def close(self) -> None:
        if self.pipeline is not None:
            Gst, _ = require_gst()
            self.pipeline.set_state(Gst.State.NULL)
            self.pipeline.get_state(2 * Gst.SECOND)
        self.pipeline = None
        self.sink = None
