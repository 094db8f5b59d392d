"""Typed configuration of the drone's camera (the ``[camera]`` table of the agent's TOML, also read by
``skycap camera serve``)."""

from __future__ import annotations

from dataclasses import dataclass

from skycap.config import ConfigError

__all__ = ["CameraConfig", "SOURCE_KINDS"]

#: "sim": the simulator's camera node publishes the frames (nothing to capture here);
#: "v4l2": a V4L2 device (``uri`` = /dev/videoN); "gstreamer": any GStreamer pipeline ending where an appsink
#: can be appended (``uri`` = the pipeline, e.g. "libcamerasrc ! videoconvert"); "rtsp": an RTSP/RTP stream
#: (``uri`` = rtsp://...); "file": a video file or a folder of images replayed at ``rate_hz`` (``uri`` = path).
SOURCE_KINDS = ("sim", "v4l2", "gstreamer", "rtsp", "file")


@dataclass
class CameraConfig:
    """Which camera this drone has and how its frames are captured and published."""

    #: one of :data:`SOURCE_KINDS`
    source: str = "sim"
    #: device path, pipeline, URL or file path (see :data:`SOURCE_KINDS`); empty for "sim"
    uri: str = ""
    camera_id: str = "cam0"
    #: requested capture size and rate (0 = the source's own); a file source replays at ``rate_hz``
    width_px: int = 0
    height_px: int = 0
    rate_hz: float = 0.0
    #: how the camera sits on the drone: "gimbal" (roll and pitch stabilised, pitch and yaw from the gimbal's
    #: reported attitude) or "fixed" (turns with the body)
    mount: str = "gimbal"
    #: fixed mount: pitch relative to the body; gimbal: the pitch assumed until the gimbal reports (deg, < 0 down)
    pitch_deg: float = -30.0
    #: the camera's optical centre in the body FRD frame (m)
    lever_arm_body_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: intrinsic calibration written by ``skycap camera calibrate`` (TOML); published as CameraInfo.
    #: Empty: only allowed with source="sim" (the simulator publishes its own CameraInfo)
    calibration_file: str = ""
    #: seconds from exposure to arrival subtracted when a source gives no capture timestamp of its own
    #: (file replay, or a pipeline without timestamps); sources that timestamp at capture ignore it
    latency_s: float = 0.0
    #: JPEG quality of the full-rate frames (``camera/image``, recorded) and of the thumbnails
    jpeg_quality: int = 90
    #: ground-station thumbnails (``camera/thumb``): rate and width (height keeps the aspect)
    thumbnail_hz: float = 1.0
    thumbnail_width_px: int = 320
    #: no frame for this long = camera lost: reported in ``camera/status`` and the source re-opened
    reconnect_after_s: float = 2.0
    #: run the capture inside the agent process (a thread) when the source is not "sim"; False = a separate
    #: ``skycap camera serve`` process (systemd unit ``skycap-camera@``) publishes the frames
    in_agent: bool = True

    def validate(self) -> "CameraConfig":
        if self.source not in SOURCE_KINDS:
            raise ConfigError(f"camera.source={self.source!r}: use one of {', '.join(SOURCE_KINDS)}")
        if self.source != "sim" and not self.uri:
            raise ConfigError(f"camera.source={self.source!r} needs camera.uri (device, pipeline, URL or path)")
        if self.source != "sim" and not self.calibration_file:
            raise ConfigError(f"camera.source={self.source!r} needs camera.calibration_file (make one with "
                              "'skycap camera calibrate ... --out camera.toml')")
        if self.mount not in ("gimbal", "fixed"):
            raise ConfigError(f"camera.mount={self.mount!r}: use 'gimbal' or 'fixed'")
        if not -90.0 <= self.pitch_deg <= 30.0:
            raise ConfigError(f"camera.pitch_deg={self.pitch_deg}: use -90 (straight down) .. 30")
        if len(self.lever_arm_body_m) != 3:
            raise ConfigError(f"camera.lever_arm_body_m={self.lever_arm_body_m}: three numbers (forward, right, down m)")
        if not 1 <= self.jpeg_quality <= 100:
            raise ConfigError(f"camera.jpeg_quality={self.jpeg_quality}: use 1..100")
        if self.rate_hz < 0 or self.thumbnail_hz < 0 or self.reconnect_after_s <= 0 or self.latency_s < 0:
            raise ConfigError("camera: rate_hz, thumbnail_hz and latency_s must be >= 0, reconnect_after_s > 0")
        return self
