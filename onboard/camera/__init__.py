"""The drone's camera: capture sources (V4L2, GStreamer, RTSP, file replay, the simulator's topic) behind one
interface, the camera service that publishes what one capture gives to the agent, the recorder, the detector and
the ground station, intrinsic calibration (ChArUco) and ``skycap camera`` (``calibrate``, ``probe``, ``serve``).

Modules: :mod:`~onboard.camera.sources` (``FrameSource``, ``open_source``, ``parse_source``; GStreamer through the
thin adapter :mod:`~onboard.camera.gst`, ``gi`` imported only when a GStreamer source opens),
:mod:`~onboard.camera.service` (``CameraService``: frames, thumbnails, CameraInfo, CameraStatus over Zenoh),
:mod:`~onboard.camera.probe`; the ``skycap camera`` command is :mod:`onboard.camera_cli`.

Time: every :class:`~onboard.camera.frame.Frame` carries ``t_capture_ns`` in the system **realtime** clock (ns
since the UNIX epoch, the time base of every ``*_ns`` field of the messages). Each source states how it gets it
(its latency model) in its docstring.
"""

from onboard.camera.config import CameraConfig, SOURCE_KINDS
from onboard.camera.frame import Frame

__all__ = ["CameraConfig", "SOURCE_KINDS", "Frame"]
