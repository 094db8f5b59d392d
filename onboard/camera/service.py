"""The camera service: one capture source -> the drone's camera topics over Zenoh.

    svc = CameraService(cfg.camera, bus, fleet="f1", drone_id="drone_1")
    svc.start()            # loads the calibration (CameraError if missing), starts the capture thread
    ...
    svc.stop()

Per drone (``skycap/v1/<fleet>/<drone>/...``, ``header.sender_id`` = the drone):

| topic | message | when |
| --- | --- | --- |
| ``camera/image`` | :class:`CameraFrame` JPEG, ``header.t_measurement_ns`` = ``Frame.t_capture_ns`` | every frame |
| ``camera/thumb`` | :class:`CameraFrame` JPEG ``thumbnail_width_px`` wide | ``thumbnail_hz`` |
| ``camera_info`` | :class:`CameraInfo` from ``calibration_file`` (latched) | start, size change, 1 Hz |
| ``camera/status`` | :class:`CameraStatus` | 1 Hz and on (dis)connection |

A source that delivers nothing for ``reconnect_after_s`` (or ends / fails) is reported (``connected=False``
with the reason in ``detail``), closed and re-opened with exponential backoff (:data:`BACKOFF_S`); a frame that
fails to encode or publish is logged and skipped: the service never dies on one. Frames the service could not
keep up with are overwritten in the source (appsink ``drop=true``, file replay skipping, the sim queue) and come
back as gaps of the source's counter: ``CameraStatus.dropped``.

The calibration is checked against the frames: another size with the same aspect ratio publishes scaled
intrinsics with a warning; another aspect ratio is an error (logged, in ``detail``) and no CameraInfo is
published, since wrong intrinsics would silently corrupt everything downstream.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import signal
import threading
import time
from typing import Any, Callable

import cv2
import numpy as np

from onboard.camera.config import CameraConfig
from onboard.camera.frame import Frame
from onboard.camera.sources import FrameSource, open_source
from shared_msgs import keys
from shared_msgs.messages import CameraFrame, CameraInfo, CameraStatus
from skycap.camera import CameraError, PinholeCamera
from skycap.config import ConfigError
from skycap.frames import R_body_cam, make_T
from skycap.sdnotify import Notifier

log = logging.getLogger(__name__)

__all__ = ["CameraService", "ServiceCounters", "scale_camera", "serve", "BACKOFF_S", "STATUS_PERIOD_S",
           "INFO_PERIOD_S"]

#: first and longest wait between re-open attempts of a lost source
BACKOFF_S = (0.5, 5.0)
STATUS_PERIOD_S = 1.0
INFO_PERIOD_S = 1.0
#: the reader waits at most this long for a frame before doing its periodic work
READ_TIMEOUT_S = 0.1


@dataclasses.dataclass
class ServiceCounters:
    frames: int = 0  #: frames published on camera/image
    thumbs: int = 0
    infos: int = 0
    statuses: int = 0
    bad_frames: int = 0  #: frames that failed to encode or publish (skipped)
    reconnects: int = 0  #: successful re-opens after a loss
    open_failures: int = 0


def scale_camera(cam: PinholeCamera, width_px: int, height_px: int) -> PinholeCamera | None:
    """``cam`` for frames of ``width_px`` x ``height_px``: itself, scaled intrinsics (same aspect ratio, 1%),
    or None (another aspect ratio: the calibration does not describe these frames)."""
    if (cam.width_px, cam.height_px) == (width_px, height_px):
        return cam
    sx, sy = width_px / cam.width_px, height_px / cam.height_px
    if abs(sx / sy - 1.0) > 0.01:
        return None
    return dataclasses.replace(cam, width_px=width_px, height_px=height_px, fx_px=cam.fx_px * sx,
                               fy_px=cam.fy_px * sy, cx_px=(cam.cx_px + 0.5) * sx - 0.5,
                               cy_px=(cam.cy_px + 0.5) * sy - 0.5)


def _jpeg(image: np.ndarray, quality: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError(f"JPEG encoding of a {image.shape} image failed")
    return buf.tobytes()


class CameraService:
    """Reads one source in a thread and publishes the camera topics of ``drone_id`` (see the module doc).

    ``bus``: an open :class:`comms.transport.Transport` (anything with ``publish(key, msg, latch=...)``).
    ``source``: a :class:`FrameSource` to use instead of the one ``cfg`` describes (tests); it is opened and
    re-opened by the service. ``notifier``: systemd's watchdog, pinged from the capture loop (``skycap camera
    serve`` under deploy/skycap-camera.service; none inside the agent, whose control loop pings it).
    """

    def __init__(self, cfg: CameraConfig, bus: Any, fleet: str, drone_id: str, *, source: FrameSource | None = None,
                 loop_file: bool = False, notifier: Notifier | None = None) -> None:
        if cfg.source == "sim" and source is None:
            raise ConfigError("camera.source='sim': the simulator's camera node publishes this drone's frames; "
                              "the camera service captures a real source (v4l2, gstreamer, rtsp or file)")
        self.cfg = cfg
        self.bus = bus
        self.fleet = fleet
        self.drone_id = drone_id
        self.source = source if source is not None else open_source(cfg, fleet=fleet, loop_file=loop_file,
                                                                    open_now=False)
        self.counters = ServiceCounters()
        self.notifier = notifier if notifier is not None else Notifier.disabled()
        self.calibration: PinholeCamera | None = None
        self.info_camera: PinholeCamera | None = None  #: what CameraInfo says now (None: not published)
        self.connected = False
        self.detail = "starting"
        self.size_error = ""
        self._key = {t: keys.drone_key(fleet, drone_id, t) for t in
                     (keys.CAMERA_IMAGE, keys.CAMERA_THUMB, keys.CAMERA_INFO, keys.CAMERA_STATUS)}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._size: tuple[int, int] | None = None
        self._frames_at_last_status = 0
        self._t_last_status = 0.0
        self._t_last_info = -1e9
        self._t_last_thumb = -1e9
        self._ever_opened = False
        self._last_log: dict[str, float] = {}
        self._last_disconnect_detail = ""
        # the mount, as CameraInfo carries it: T_body_cam at zero gimbal angles (a fixed mount's pitch inside it),
        # and for a gimbal the pitch assumed until the gimbal reports (its reports are recorded on <drone>/gimbal)
        pitch = math.radians(cfg.pitch_deg)
        R = R_body_cam(0.0 if cfg.mount == "gimbal" else pitch)
        self._T_body_cam = tuple(float(v) for v in make_T(R, np.asarray(cfg.lever_arm_body_m, dtype=float)).ravel())
        self._info_pitch_rad = pitch if cfg.mount == "gimbal" else 0.0

    # ------------------------------------------------------------------------------------------ life
    def start(self) -> "CameraService":
        """Load the calibration (a :class:`CameraError` naming the file when it is missing or invalid), publish
        CameraInfo, start the capture thread."""
        if self.cfg.calibration_file:
            self.calibration = PinholeCamera.from_toml(self.cfg.calibration_file)
        elif self.cfg.source != "sim":
            raise CameraError(f"camera {self.cfg.camera_id}: no camera.calibration_file; make one with 'skycap "
                              "camera calibrate SOURCE ... --out camera.toml' and set camera.calibration_file")
        self.info_camera = self.calibration
        self._publish_info()
        self._thread = threading.Thread(target=self._run, name=f"camera-{self.drone_id}", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.warning("camera service of %s: capture thread still running after %.1f s", self.drone_id,
                            timeout_s)
        self._thread = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # ------------------------------------------------------------------------------------------ loop
    def _run(self) -> None:
        cfg, src = self.cfg, self.source
        is_open = False
        t_next_open = 0.0
        backoff = BACKOFF_S[0]
        t_ref = time.monotonic()  # last frame or open
        try:
            while not self._stop.is_set():
                self.notifier.watchdog()  # a capture loop stuck in the source stops it: systemd restarts the service
                now = time.monotonic()
                if not is_open:
                    if now >= t_next_open:
                        try:
                            src.open()
                            is_open, t_ref = True, time.monotonic()
                            if self._ever_opened:
                                self.counters.reconnects += 1
                                log.info("camera %s: %s re-opened", cfg.camera_id, src.describe())
                            self._ever_opened = True
                            self.detail = "opened, waiting for frames"
                        except Exception as e:  # keep trying: the camera may come (back) later
                            self.counters.open_failures += 1
                            self._set_disconnected(f"cannot open {src.describe()}: {e}")
                            t_next_open = now + backoff
                            backoff = min(backoff * 2, BACKOFF_S[1])
                    else:
                        self._stop.wait(min(0.05, t_next_open - now))
                else:
                    frame = None
                    try:
                        frame = src.read(READ_TIMEOUT_S)
                    except Exception as e:
                        self._log_limited("read", logging.WARNING, "camera %s: read failed: %s", cfg.camera_id, e)
                    now = time.monotonic()
                    if frame is not None:
                        t_ref = now
                        backoff = BACKOFF_S[0]
                        if not self.connected:
                            self.connected = True
                            self.detail = ""
                            log.info("camera %s: %s delivering %dx%d", cfg.camera_id, src.describe(),
                                     frame.width_px, frame.height_px)
                            self._publish_status()
                        self._publish_frame(frame)
                    elif src.ended or now - t_ref > cfg.reconnect_after_s:
                        if src.ended:
                            why = src.stats.last_error or "the stream ended"
                            detail = f"{src.describe()} lost: {why} (last frame {now - t_ref:.1f} s ago)"
                        else:
                            detail = f"{src.describe()}: no frame for {now - t_ref:.1f} s"
                        self._set_disconnected(detail)
                        try:
                            src.close()
                        except Exception as e:
                            log.debug("closing %s: %s", src.describe(), e)
                        is_open = False
                        t_next_open = now + backoff
                        backoff = min(backoff * 2, BACKOFF_S[1])
                self._periodic()
        finally:
            try:
                src.close()
            except Exception as e:
                log.debug("closing %s: %s", src.describe(), e)
            self.connected = False
            self.detail = "stopped"
            self._publish_status()

    def _set_disconnected(self, detail: str) -> None:
        was = self.connected
        self.connected = False
        self.detail = detail
        if was or self._last_disconnect_detail != detail:
            log.warning("camera %s: %s", self.cfg.camera_id, detail)
            self._last_disconnect_detail = detail
        if was:
            self._publish_status()

    def _periodic(self) -> None:
        now = time.monotonic()
        if now - self._t_last_status >= STATUS_PERIOD_S:
            self._publish_status()
        if now - self._t_last_info >= INFO_PERIOD_S:
            self._publish_info()

    def _log_limited(self, what: str, level: int, fmt: str, *args: Any) -> None:
        now = time.monotonic()
        if now - float(self._last_log.get(what, -1e9)) >= 5.0:
            self._last_log[what] = now
            log.log(level, fmt, *args)

    # --------------------------------------------------------------------------------------- publish
    def _check_size(self, w: int, h: int) -> None:
        self._size = (w, h)
        cal = self.calibration
        if cal is None:
            return
        cam = scale_camera(cal, w, h)
        if cam is None:
            self.size_error = (f"calibration {self.cfg.calibration_file} is for {cal.width_px}x{cal.height_px} "
                               f"but the frames are {w}x{h} (another aspect ratio): no CameraInfo published; "
                               "calibrate this mode or set camera.width_px/height_px to the calibrated size")
            log.error("camera %s: %s", self.cfg.camera_id, self.size_error)
        else:
            self.size_error = ""
            if cam is not cal:
                log.warning("camera %s: calibration %s is for %dx%d, frames are %dx%d: publishing intrinsics "
                            "scaled by %.3f", self.cfg.camera_id, self.cfg.calibration_file, cal.width_px,
                            cal.height_px, w, h, w / cal.width_px)
        if cam != self.info_camera:
            self.info_camera = cam
            self._publish_info()

    def _publish_frame(self, f: Frame) -> None:
        cfg = self.cfg
        try:
            if self._size != (f.width_px, f.height_px):
                self._check_size(f.width_px, f.height_px)
            msg = CameraFrame(
                header=CameraFrame.make_header(self.drone_id, f.t_capture_ns, f.frame_index),
                camera_id=cfg.camera_id, frame_index=int(f.frame_index), encoding="jpeg",
                width_px=f.width_px, height_px=f.height_px, data=_jpeg(f.image, cfg.jpeg_quality),
                exposure_s=f.exposure_s, source=self.source.describe(),
            )  # fmt: skip
            self.bus.publish(self._key[keys.CAMERA_IMAGE], msg)
            self.counters.frames += 1
            now = time.monotonic()
            if cfg.thumbnail_hz > 0 and now - self._t_last_thumb >= 1.0 / cfg.thumbnail_hz:
                self._t_last_thumb = now
                self._publish_thumb(f)
        except Exception as e:  # one bad frame never stops the camera
            self.counters.bad_frames += 1
            self._log_limited("frame", logging.WARNING, "camera %s: frame %d skipped: %s", cfg.camera_id,
                              f.frame_index, e)

    def _publish_thumb(self, f: Frame) -> None:
        cfg = self.cfg
        img = f.image
        if cfg.thumbnail_width_px > 0 and img.shape[1] > cfg.thumbnail_width_px:
            h = max(1, round(img.shape[0] * cfg.thumbnail_width_px / img.shape[1]))
            img = cv2.resize(img, (cfg.thumbnail_width_px, h), interpolation=cv2.INTER_AREA)
        msg = CameraFrame(
            header=CameraFrame.make_header(self.drone_id, f.t_capture_ns, f.frame_index),
            camera_id=cfg.camera_id, frame_index=int(f.frame_index), encoding="jpeg",
            width_px=int(img.shape[1]), height_px=int(img.shape[0]), data=_jpeg(img, cfg.jpeg_quality),
            exposure_s=f.exposure_s, source=self.source.describe(),
        )  # fmt: skip
        self.bus.publish(self._key[keys.CAMERA_THUMB], msg)
        self.counters.thumbs += 1

    def camera_info(self) -> CameraInfo | None:
        c = self.info_camera
        if c is None or self.size_error:
            return None
        return CameraInfo(
            header=CameraInfo.make_header(self.drone_id),
            camera_id=self.cfg.camera_id, width_px=c.width_px, height_px=c.height_px,
            fx_px=c.fx_px, fy_px=c.fy_px, cx_px=c.cx_px, cy_px=c.cy_px,
            distortion_model=c.distortion_model,  # type: ignore[arg-type]
            distortion=tuple(c.distortion) if c.distortion_model != "none" else (),
            T_body_cam=self._T_body_cam, gimbal_pitch_rad=self._info_pitch_rad,
        )  # fmt: skip

    def _publish_info(self) -> None:
        self._t_last_info = time.monotonic()
        msg = self.camera_info()
        if msg is None:
            return
        try:
            self.bus.publish(self._key[keys.CAMERA_INFO], msg, latch=True)
            self.counters.infos += 1
        except Exception as e:
            self._log_limited("info", logging.WARNING, "camera %s: CameraInfo not published: %s", self.cfg.camera_id, e)

    def status(self) -> CameraStatus:
        now = time.monotonic()
        dt = now - self._t_last_status if self._t_last_status else 0.0
        rate = (self.counters.frames - self._frames_at_last_status) / dt if dt > 0 else 0.0
        detail = self.detail or self.size_error
        if self.detail and self.size_error:
            detail = f"{self.detail}; {self.size_error}"
        return CameraStatus(
            header=CameraStatus.make_header(self.drone_id),
            camera_id=self.cfg.camera_id, source=self.source.describe(), connected=self.connected,
            frames=self.counters.frames, dropped=int(self.source.stats.dropped),
            reconnects=self.counters.reconnects, rate_hz=float(rate), latency_s=float(self.source.latency_s),
            detail=detail,
        )  # fmt: skip

    def _publish_status(self) -> None:
        msg = self.status()
        self._t_last_status = time.monotonic()
        self._frames_at_last_status = self.counters.frames
        try:
            self.bus.publish(self._key[keys.CAMERA_STATUS], msg)
            self.counters.statuses += 1
        except Exception as e:
            self._log_limited("status", logging.WARNING, "camera %s: status not published: %s", self.cfg.camera_id, e)


def serve(agent_cfg: Any, *, stop: threading.Event | None = None,
          on_started: Callable[[CameraService], None] | None = None) -> int:
    """``skycap camera serve``: run the camera service of ``agent_cfg`` (an :class:`onboard.config.AgentConfig`:
    its ``camera``, ``fleet``, ``drone_id``, ``transport``) until SIGTERM/SIGINT (or ``stop`` is set)."""
    from comms.transport import Transport

    cam_cfg: CameraConfig = agent_cfg.camera.validate()
    notifier = Notifier.from_env()
    notifier.status(f"camera {cam_cfg.camera_id} of {agent_cfg.drone_id}: starting")
    stop = stop or threading.Event()
    restore: list[tuple[int, Any]] = []
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            restore.append((sig, signal.signal(sig, lambda signum, _frame: stop.set())))
    try:
        with Transport.open(agent_cfg.transport, node_id=f"{agent_cfg.drone_id}-camera", identity=agent_cfg.drone_id) as bus:
            # a file served as a camera (bench tests) replays in a loop rather than re-opening after each end
            svc = CameraService(cam_cfg, bus, agent_cfg.fleet, agent_cfg.drone_id,
                                loop_file=cam_cfg.source == "file", notifier=notifier).start()
            log.info("camera %s of %s: serving %s on %s", cam_cfg.camera_id, agent_cfg.drone_id,
                     svc.source.describe(), keys.drone_key(agent_cfg.fleet, agent_cfg.drone_id, "camera/*"))
            if on_started is not None:
                on_started(svc)
            # ready once publishing (the calibration loaded, the capture running): a camera that is absent or lost
            # is reported in camera/status and re-opened, not waited for here
            notifier.ready(f"camera {cam_cfg.camera_id}: {svc.source.describe()}: {svc.detail}")
            try:
                while not stop.wait(0.5):
                    if not svc.running:
                        log.error("camera service thread ended")
                        return 1
                    notifier.status(f"camera {cam_cfg.camera_id}: {svc.source.describe()}: "
                                    + ("delivering" if svc.connected else svc.detail))
            finally:
                notifier.stopping(f"camera {cam_cfg.camera_id}: stopping")
                svc.stop()
                c = svc.counters
                log.info("camera %s: stopped after %d frames (%d dropped by the source, %d bad, %d reconnects)",
                         cam_cfg.camera_id, c.frames, svc.source.stats.dropped, c.bad_frames, c.reconnects)
    finally:
        for sig, old in restore:
            signal.signal(sig, old)
    return 0
