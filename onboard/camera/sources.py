"""Camera capture sources behind one interface.

    from onboard.camera.sources import open_source, parse_source

    kind, uri = parse_source("v4l2:/dev/video0")          # CLI strings -> (kind, uri)
    with open_source(CameraConfig(source=kind, uri=uri)) as src:   # opened
        frame = src.read(timeout_s=1.0)                      # Frame, or None (nothing yet / ended)
        print(src.describe(), src.stats)

Sources (:data:`~onboard.camera.config.SOURCE_KINDS`), each with its **latency model** (how
``Frame.t_capture_ns`` is obtained) in its docstring: :class:`V4L2Source`, :class:`GStreamerSource`,
:class:`RtspSource` (GStreamer, :mod:`onboard.camera.gst`), :class:`FileSource` (OpenCV) and :class:`SimSource`
(the simulator's ``camera/image`` topic over Zenoh).

Every source counts ``stats.frames`` (delivered) and ``stats.dropped`` (frames lost before the reader got them:
gaps in the source's own frame counter, or in the PTS at the negotiated frame rate, or frames a slow reader let
the source overwrite). A gap is counted once; a counter that goes back (a stream restarted) is not a gap.
"""

from __future__ import annotations

import logging
import os
import queue
import re
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from onboard.camera.config import SOURCE_KINDS, CameraConfig
from onboard.camera.errors import CameraSourceError
from onboard.camera.frame import Frame

log = logging.getLogger(__name__)

__all__ = [
    "CameraSourceError",
    "SourceStats",
    "FrameSource",
    "GStreamerSource",
    "V4L2Source",
    "RtspSource",
    "FileSource",
    "SimSource",
    "open_source",
    "parse_source",
    "RTSP_JITTER_LATENCY_MS",
    "IMAGE_EXTENSIONS",
]

#: rtspsrc's jitterbuffer latency: frames leave it this long after their packets arrived
RTSP_JITTER_LATENCY_MS = 100
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
SOURCE_FORMS = ("v4l2:/dev/video0", "gst:<pipeline> (or gstreamer:<pipeline>)", "rtsp://host:port/path",
                "file:<video or image folder> (or an existing path)", "sim:<drone_id>")


@dataclass
class SourceStats:
    """Counters of one source (across re-opens of the same object)."""

    frames: int = 0  #: frames delivered by read()
    dropped: int = 0  #: frames lost before read() got them
    opens: int = 0
    last_error: str = ""


class FrameSource(ABC):
    """One camera capture: ``open()``, then ``read(timeout_s)`` until ``ended``, then ``close()``.

    ``read`` returns a :class:`Frame` or None (no frame within ``timeout_s``, or the stream ended / failed:
    ``ended`` is then True and ``stats.last_error`` says why). Not thread-safe: one reader thread.
    ``latency_model`` states how the capture time is obtained (shown by ``probe`` and in ``camera/status``).
    """

    kind: str = ""
    latency_model: str = ""
    #: seconds subtracted from arrival times (0 when the source timestamps at capture)
    latency_s: float = 0.0

    def __init__(self) -> None:
        self.stats = SourceStats()
        self._last_index: int | None = None

    @abstractmethod
    def describe(self) -> str:
        """e.g. "v4l2:/dev/video0", "rtsp://...", "file:flight.mp4"."""

    @abstractmethod
    def open(self) -> None:
        """Start capturing; raises :class:`CameraSourceError` naming the problem and the fix."""

    @abstractmethod
    def read(self, timeout_s: float = 1.0) -> Frame | None:
        ...

    @abstractmethod
    def close(self) -> None:
        ...

    @property
    def ended(self) -> bool:
        return False

    def _account(self, index: int) -> None:
        """Count a delivered frame with the source's counter ``index`` (gaps = dropped)."""
        last = self._last_index
        if last is not None and index > last + 1:
            self.stats.dropped += index - last - 1
        self._last_index = index
        self.stats.frames += 1

    def __enter__(self) -> "FrameSource":
        self.open()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.describe()}>"


# ------------------------------------------------------------------------------------------------- GStreamer
class _GstFrameSource(FrameSource):
    """Common part of the GStreamer sources: frame index from the buffer offset when the source sets it, else
    an own counter advanced by the PTS gaps at the negotiated frame rate."""

    def __init__(self, *, pts_latency_s: float = 0.0, fallback_latency_s: float = 0.0, use_ntp_meta: bool = False,
                 size: tuple[int, int] = (0, 0)) -> None:
        super().__init__()
        self.pts_latency_s = float(pts_latency_s)
        self.fallback_latency_s = float(fallback_latency_s)
        self.latency_s = self.pts_latency_s
        self.use_ntp_meta = use_ntp_meta
        self.size = size
        self._gst = None
        self._counter = -1
        self._last_pts: int | None = None

    @abstractmethod
    def pipeline_description(self) -> str:
        """The pipeline up to (not including) the conversion to BGR and the appsink."""

    def _check_before_open(self) -> None:
        pass

    def open(self) -> None:
        from onboard.camera.gst import GstSource

        self._check_before_open()
        self.close()
        g = GstSource(self.pipeline_description(), name=self.describe(), latency_s=self.pts_latency_s,
                      arrival_latency_s=self.fallback_latency_s, use_ntp_meta=self.use_ntp_meta, size=self.size)
        try:
            g.open()
        except CameraSourceError as e:
            self.stats.last_error = str(e)
            raise
        self._gst = g
        self._last_index = -1  # a fresh pipeline counts from 0: frames before the first one we get were dropped
        self._last_pts = None
        self.stats.opens += 1
        log.info("%s: opened (%s)", self.describe(), self.latency_model)

    @property
    def ended(self) -> bool:
        return self._gst is None or self._gst.ended

    @property
    def gst(self) -> Any:
        """The :class:`onboard.camera.gst.GstSource` adapter while open (None when closed)."""
        return self._gst

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        g = self._gst
        if g is None:
            return None
        got = g.pull(timeout_s)
        if got is None:
            if g.error:
                self.stats.last_error = g.error
            return None
        image, t_capture_ns, index, t_received_ns, pts = got
        if index is None:  # no source counter: own counter, advanced by the PTS gaps at the negotiated rate
            step = 1
            rate = g.framerate_hz()
            if self._last_pts is not None and pts is not None and rate > 0:
                step = max(1, int(round((pts - self._last_pts) * rate / 1e9)))
            self._counter += step
            index = self._counter
            if pts is not None:
                self._last_pts = pts
        self._account(index)
        return Frame(image=image, t_capture_ns=int(t_capture_ns), frame_index=int(index),
                     t_received_ns=int(t_received_ns), exposure_s=None)

    def close(self) -> None:
        if self._gst is not None:
            self._gst.close()
            self._gst = None


class GStreamerSource(_GstFrameSource):
    """Any GStreamer pipeline (``camera.uri``), e.g. ``libcamerasrc ! video/x-raw,width=1280,height=720``; the
    source appends ``videoconvert ! video/x-raw,format=BGR ! appsink``.

    Latency model: the buffer PTS (running time) + the pipeline's base time is the pipeline-clock time the
    source stamped (live sources stamp at capture: libcamerasrc the sensor timestamp, videotestsrc the clock
    time it made the frame); converted to realtime by one clock offset. Buffers without a PTS: arrival time
    minus ``camera.latency_s``.
    """

    kind = "gstreamer"
    latency_model = "pipeline PTS (the source's own capture stamp)"

    def __init__(self, pipeline: str, *, latency_s: float = 0.0, size: tuple[int, int] = (0, 0)) -> None:
        super().__init__(fallback_latency_s=latency_s, size=size)
        self.pipeline = pipeline.strip().rstrip("!").strip()
        if not self.pipeline:
            raise CameraSourceError("gstreamer source: empty pipeline; write e.g. 'gst:videotestsrc is-live=true'")

    def describe(self) -> str:
        return f"gstreamer:{self.pipeline}"

    def pipeline_description(self) -> str:
        return self.pipeline


class V4L2Source(_GstFrameSource):
    """A V4L2 device (``/dev/videoN``) through GStreamer's ``v4l2src`` (raw or MJPEG, decoded).

    Latency model: v4l2src stamps each buffer with the **driver's capture timestamp** (converted to the
    pipeline clock): UVC webcams stamp when the frame's first USB packet arrived (end of exposure, start of
    readout), CSI drivers at start or end of frame. That is the capture time; ``camera.latency_s`` is not used.
    The frame index is the driver's sequence number (buffer offset), so the driver's own drops are counted.
    """

    kind = "v4l2"
    latency_model = "driver capture timestamp (v4l2 buffer)"

    def __init__(self, device: str, *, size: tuple[int, int] = (0, 0), rate_hz: float = 0.0,
                 latency_s: float = 0.0) -> None:
        super().__init__(fallback_latency_s=latency_s, size=(0, 0))
        self.device = device
        self.req_size = size
        self.rate_hz = float(rate_hz)

    def describe(self) -> str:
        return f"v4l2:{self.device}"

    def _check_before_open(self) -> None:
        if not os.path.exists(self.device):
            msg = (f"V4L2 device {self.device} not found; list the cameras with 'v4l2-ctl --list-devices' "
                   "(package v4l-utils) and set camera.uri to one of their /dev/videoN")
            self.stats.last_error = msg
            raise CameraSourceError(msg)

    def pipeline_description(self) -> str:
        w, h = self.req_size
        fields = ""
        if w > 0 and h > 0:
            fields += f",width={int(w)},height={int(h)}"
        if self.rate_hz > 0:
            fields += f",framerate={int(round(self.rate_hz))}/1"
        caps = f' ! capsfilter caps="video/x-raw{fields};image/jpeg{fields}"' if fields else ""
        return f"v4l2src device={self.device}{caps} ! decodebin"


class RtspSource(_GstFrameSource):
    """An RTSP/RTP stream through ``rtspsrc location=... latency=N ! decodebin``.

    Latency model: rtspsrc's jitterbuffer gives each frame a PTS at its (skew-corrected) **arrival** and
    delivers it :data:`RTSP_JITTER_LATENCY_MS` later. When the stream's RTCP sender reports have arrived,
    buffers carry a ``timestamp/x-ntp`` reference meta (``add-reference-timestamp-meta``): the **sender's**
    capture time in NTP, used as is (needs the sender's clock synchronised with ours, e.g. by chrony/PTP).
    Before that, or without RTCP: arrival (PTS) minus ``camera.latency_s`` (set it to the camera's
    encode + network latency, measured once e.g. by filming a clock).
    """

    kind = "rtsp"

    def __init__(self, url: str, *, latency_s: float = 0.0, size: tuple[int, int] = (0, 0),
                 jitter_latency_ms: int = RTSP_JITTER_LATENCY_MS) -> None:
        super().__init__(pts_latency_s=latency_s, fallback_latency_s=latency_s, use_ntp_meta=True, size=size)
        self.url = url
        self.jitter_latency_ms = int(jitter_latency_ms)
        self.latency_model = (f"sender NTP time (RTCP) when known, else arrival - {latency_s:.3f} s "
                              f"(jitterbuffer {self.jitter_latency_ms} ms)")

    def describe(self) -> str:
        return self.url

    @property
    def ntp_frames(self) -> int:
        """Frames timed by the sender's NTP reference (since the last open)."""
        return 0 if self._gst is None else self._gst.ntp_frames

    def pipeline_description(self) -> str:
        return (f"rtspsrc location={self.url} latency={self.jitter_latency_ms} add-reference-timestamp-meta=true "
                "! decodebin")


# ------------------------------------------------------------------------------------------------- file replay
def _natural_key(p: Path) -> list[Any]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", p.name)]


class FileSource(FrameSource):
    """A video file (OpenCV) or a folder of images (natural sort: img2 before img10) replayed in real time at
    ``rate_hz`` (default: the video's fps, or 10 Hz for images), as a camera would deliver them.

    Latency model: ``t_capture = time the frame is handed over - camera.latency_s``. A reader slower than the
    rate makes the replay skip frames (counted as dropped), as a live camera would. ``loop=False``: at the end
    ``read`` returns None and ``ended`` is True; ``loop=True`` starts again (the frame index restarts at 0).
    ``realtime=False`` hands frames over as fast as they are read (tests, offline processing).
    """

    kind = "file"
    latency_model = "replay time - latency_s"

    def __init__(self, path: str | Path, *, rate_hz: float = 0.0, latency_s: float = 0.0, loop: bool = False,
                 size: tuple[int, int] = (0, 0), realtime: bool = True) -> None:
        super().__init__()
        self.path = Path(path)
        self.req_rate_hz = float(rate_hz)
        self.latency_s = float(latency_s)
        self.loop = loop
        self.size = size
        self.realtime = realtime
        self.rate_hz = 0.0
        self.frame_count = 0
        self._cap: Any = None
        self._images: list[Path] = []
        self._next = 0
        self._t0 = 0.0
        self._i0 = 0
        self._ended = False

    def describe(self) -> str:
        return f"file:{self.path}"

    def open(self) -> None:
        import cv2

        self.close()
        p = self.path
        if p.is_dir():
            self._images = sorted((q for q in p.iterdir() if q.suffix.lower() in IMAGE_EXTENSIONS), key=_natural_key)
            if not self._images:
                raise self._fail(f"file source: folder {p} holds no images ({', '.join(IMAGE_EXTENSIONS)})")
            self.frame_count = len(self._images)
            self.rate_hz = self.req_rate_hz or 10.0
        elif p.is_file():
            cap = cv2.VideoCapture(str(p))
            if not cap.isOpened():
                raise self._fail(f"file source: OpenCV cannot read {p} as a video (use a video file, e.g. .mp4/.avi, "
                                 "or a folder of images)")
            self._cap = cap
            self.frame_count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
            fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
            self.rate_hz = self.req_rate_hz or (fps if 0 < fps < 1000 else 10.0)
        else:
            raise self._fail(f"file source: {p} does not exist (give a video file or a folder of images)")
        self._next = 0
        self._restart_clock()
        self._ended = False
        self._last_index = None
        self.stats.opens += 1

    def _fail(self, msg: str) -> CameraSourceError:
        self.stats.last_error = msg
        return CameraSourceError(msg)

    def _restart_clock(self) -> None:
        self._t0, self._i0 = time.monotonic(), self._next

    @property
    def ended(self) -> bool:
        return self._ended

    def _grab(self, decode: bool) -> np.ndarray | None:
        """Frame ``self._next`` (decoded or only skipped); None at the end."""
        import cv2

        i = self._next
        if self._images:
            if i >= len(self._images):
                return None
            self._next += 1
            if not decode:
                return np.empty(0)
            img = cv2.imread(str(self._images[i]), cv2.IMREAD_COLOR)
            if img is None:
                log.warning("file source: cannot read image %s; skipped (counted as dropped)", self._images[i])
                return np.empty(0)
            return img
        if self._cap is None:
            return None
        ok = self._cap.grab()
        if not ok:
            return None
        self._next += 1
        if not decode:
            return np.empty(0)
        ok, img = self._cap.retrieve()
        return img if ok else np.empty(0)

    def _rewind(self) -> None:
        import cv2

        self._next = 0
        if self._cap is not None:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
        self._restart_clock()

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        import cv2

        if self._ended or (self._cap is None and not self._images):
            return None
        while True:
            if self.realtime:
                due = self._t0 + (self._next - self._i0) / self.rate_hz
                now = time.monotonic()
                if due - now > timeout_s:
                    time.sleep(max(0.0, timeout_s))
                    return None
                if due > now:
                    time.sleep(due - now)
                else:  # late: skip the frames whose time has passed (a live camera would have overwritten them);
                    # the gap in the frame index counts them as dropped
                    late = int((now - due) * self.rate_hz)
                    for _ in range(late):
                        if self._grab(decode=False) is None:
                            break
            index = self._next
            img = self._grab(decode=True)
            if img is None:  # end of the file
                if self.loop and index > 0:
                    self._rewind()
                    continue
                self._ended = True
                return None
            if img.size == 0:
                continue
            break
        w, h = self.size
        if w > 0 and h > 0 and (img.shape[1], img.shape[0]) != (w, h):
            img = cv2.resize(img, (int(w), int(h)), interpolation=cv2.INTER_AREA)
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        t_received_ns = time.time_ns()
        self._account(index)
        return Frame(image=np.ascontiguousarray(img), t_capture_ns=t_received_ns - int(self.latency_s * 1e9),
                     frame_index=index, t_received_ns=t_received_ns)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
        self._cap = None
        self._images = []


# ------------------------------------------------------------------------------------------------- simulator
class SimSource(FrameSource):
    """The simulator's camera of ``drone_id``: its ``camera/image`` frames over Zenoh, JPEG-decoded.

    Latency model: the simulator's ``header.t_measurement_ns`` (the simulated capture time) as is; the frame
    index is the message's. ``bus``: an open :class:`comms.transport.Transport` (else one is opened from
    ``transport`` and closed with the source). A reader slower than the frames keeps the newest
    (:data:`QUEUE_FRAMES`); the ones it overwrote count as dropped.
    """

    kind = "sim"
    latency_model = "simulator capture time (message header)"
    QUEUE_FRAMES = 2

    def __init__(self, drone_id: str, *, fleet: str = "default", bus: Any = None, transport: Any = None) -> None:
        super().__init__()
        if not drone_id:
            raise CameraSourceError("sim source: name the drone, e.g. 'sim:drone_1'")
        self.drone_id = drone_id
        self.fleet = fleet
        self._bus = bus
        self._own_bus = False
        self._transport_cfg = transport
        self._sub: Any = None
        self._q: queue.Queue = queue.Queue(maxsize=self.QUEUE_FRAMES)
        self._lock = threading.Lock()

    def describe(self) -> str:
        return f"sim:{self.drone_id}"

    def open(self) -> None:
        from comms.transport import Transport
        from shared_msgs import keys
        from shared_msgs.messages import CameraFrame

        self.close()
        if self._bus is None or self._own_bus:
            self._bus = Transport.open(self._transport_cfg, node_id=f"camera-probe-{self.drone_id}",
                                      identity=self.drone_id)
            self._own_bus = True
        key = keys.drone_key(self.fleet, self.drone_id, keys.CAMERA_IMAGE)
        self._sub = self._bus.subscribe(key, self._on_frame, CameraFrame)
        self._last_index = None
        self.stats.opens += 1

    def _on_frame(self, rx: Any) -> None:  # Zenoh's thread: keep it short
        with self._lock:
            while True:
                try:
                    self._q.put_nowait(rx)
                    return
                except queue.Full:  # overwrite the oldest (the frame-index gap counts it as dropped)
                    try:
                        self._q.get_nowait()
                    except queue.Empty:
                        pass

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        import cv2

        try:
            rx = self._q.get(timeout=max(0.0, timeout_s))
        except queue.Empty:
            return None
        m = rx.msg
        img = cv2.imdecode(np.frombuffer(m.data, np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            self.stats.last_error = f"frame {m.frame_index}: cannot decode its {m.encoding} data"
            return None  # the next frame's index gap counts it as dropped
        self._account(int(m.frame_index))
        return Frame(image=img, t_capture_ns=int(m.header.t_measurement_ns), frame_index=int(m.frame_index),
                     t_received_ns=int(rx.t_received_ns), exposure_s=m.exposure_s)

    def close(self) -> None:
        if self._sub is not None:
            self._sub.close()
            self._sub = None
        if self._own_bus and self._bus is not None:
            self._bus.close()
            self._bus = None


# ------------------------------------------------------------------------------------------------- factory
def parse_source(text: str) -> tuple[str, str]:
    """A CLI source string -> ``(kind, uri)``: "v4l2:/dev/video0", "gst:<pipeline>" / "gstreamer:<pipeline>",
    "rtsp://...", "file:<path>" or an existing path (a /dev/video* path is v4l2), "sim:<drone_id>"."""
    t = text.strip()
    low = t.lower()
    for prefix, kind in (("v4l2:", "v4l2"), ("gstreamer:", "gstreamer"), ("gst:", "gstreamer"), ("file:", "file"),
                         ("sim:", "sim")):
        if low.startswith(prefix):
            uri = t[len(prefix):].strip()
            if not uri:
                raise CameraSourceError(f"camera source {text!r}: nothing after {prefix!r}; forms: "
                                        + ", ".join(SOURCE_FORMS))
            return kind, uri
    if low.startswith(("rtsp://", "rtsps://", "rtspt://")):
        return "rtsp", t
    if t.startswith("/dev/video"):
        return "v4l2", t
    if t and Path(t).exists():
        return "file", t
    raise CameraSourceError(f"camera source {text!r} not understood (and no such file); forms: "
                            + ", ".join(SOURCE_FORMS))


def open_source(cfg: CameraConfig, *, bus: Any = None, fleet: str = "default", transport: Any = None,
                loop_file: bool = False, open_now: bool = True) -> FrameSource:
    """The source ``cfg`` describes (``source`` + ``uri``, size, rate, latency_s), opened unless ``open_now`` is
    False. "sim" reads drone ``cfg.uri``'s frames over ``bus`` (or a Transport opened from ``transport``)."""
    kind, uri = cfg.source, cfg.uri
    if kind not in SOURCE_KINDS:
        raise CameraSourceError(f"camera.source={kind!r}: use one of {', '.join(SOURCE_KINDS)}")
    size = (int(cfg.width_px), int(cfg.height_px))
    src: FrameSource
    if kind == "v4l2":
        src = V4L2Source(uri, size=size, rate_hz=cfg.rate_hz, latency_s=cfg.latency_s)
    elif kind == "gstreamer":
        src = GStreamerSource(uri, latency_s=cfg.latency_s, size=size)
    elif kind == "rtsp":
        src = RtspSource(uri, latency_s=cfg.latency_s, size=size)
    elif kind == "file":
        src = FileSource(uri, rate_hz=cfg.rate_hz, latency_s=cfg.latency_s, loop=loop_file, size=size)
    else:
        src = SimSource(uri, fleet=fleet, bus=bus, transport=transport)
    if open_now:
        src.open()
    return src
