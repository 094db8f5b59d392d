"""The one camera model: pinhole intrinsics with optional OpenCV distortion, posed by ``T_world_cam``.

    from skycap.camera import PinholeCamera

    cam = PinholeCamera.from_fov(width_px=960, height_px=540, hfov_deg=70.0)
    cam = PinholeCamera.from_camera_info(info)          # the CameraInfo message a drone publishes
    uv, depth_m = cam.project(T_world_cam, points_world_ned_m)   # (..., 2) pixels, (...,) depth along +z

Frames (:mod:`skycap.frames`): camera = OpenCV optical (x right, y down, z forward); ``T_world_cam`` maps
camera coordinates to world NED. Used by the simulator's renderer and camera node, the onboard tracking
measurement model and the offline track refinement; the ``CameraInfo`` message is its wire form.

Distortion: ``"none"`` or ``"plumb_bob"`` (OpenCV's radial-tangential ``(k1, k2, p1, p2, k3)``), applied by
:meth:`PinholeCamera.project_cam` to normalised coordinates as ``cv2.projectPoints`` does.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal, Protocol

import numpy as np

from skycap.errors import SkycapError
from skycap.frames import invert_T

__all__ = ["PinholeCamera", "CameraError"]

DistortionModel = Literal["none", "plumb_bob"]


class CameraError(SkycapError):
    """Camera parameters that describe no camera (non-positive size or focal length, bad distortion)."""


class _CameraInfoLike(Protocol):
    """What :meth:`PinholeCamera.from_camera_info` reads (the ``shared_msgs.CameraInfo`` message's fields;
    the core does not import the message contract, which sits a layer above it)."""

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    distortion_model: str
    distortion: tuple[float, ...]


class _FovConfig(Protocol):
    width_px: int
    height_px: int
    hfov_deg: float


@dataclasses.dataclass(frozen=True, kw_only=True)
class PinholeCamera:
    """Pinhole intrinsics in pixels (square-pixel or not), image size, and lens distortion."""

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    distortion_model: DistortionModel = "none"
    #: plumb_bob: (k1, k2, p1, p2, k3); empty for "none"
    distortion: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if not (self.width_px > 0 and self.height_px > 0 and self.fx_px > 0 and self.fy_px > 0):
            raise CameraError(f"camera {self.width_px}x{self.height_px} px with fx={self.fx_px}, fy={self.fy_px}: "
                              "size and focal lengths must be > 0")
        if self.distortion_model == "plumb_bob" and len(self.distortion) != 5:
            raise CameraError(f"plumb_bob distortion needs (k1, k2, p1, p2, k3), got {self.distortion}")
        if self.distortion_model not in ("none", "plumb_bob"):
            raise CameraError(f"distortion_model {self.distortion_model!r}: use 'none' or 'plumb_bob'")

    # --------------------------------------------------------------------------------------- builders
    @classmethod
    def from_fov(cls, width_px: int, height_px: int, hfov_deg: float) -> PinholeCamera:
        """Square pixels, centred principal point, fx = (width/2) / tan(hfov/2), no distortion."""
        f = 0.5 * width_px / math.tan(math.radians(hfov_deg) / 2)
        return cls(width_px=int(width_px), height_px=int(height_px), fx_px=f, fy_px=f, cx_px=0.5 * width_px,
                   cy_px=0.5 * height_px)

    @classmethod
    def from_config(cls, cfg: _FovConfig) -> PinholeCamera:
        """From any config with ``width_px``, ``height_px`` and ``hfov_deg`` (the simulator's camera)."""
        return cls.from_fov(cfg.width_px, cfg.height_px, cfg.hfov_deg)

    @classmethod
    def from_camera_info(cls, info: _CameraInfoLike) -> PinholeCamera:
        """From the ``CameraInfo`` message (intrinsics and distortion; the mount is the message's own)."""
        return cls(width_px=int(info.width_px), height_px=int(info.height_px), fx_px=float(info.fx_px),
                   fy_px=float(info.fy_px), cx_px=float(info.cx_px), cy_px=float(info.cy_px),
                   distortion_model=info.distortion_model, distortion=tuple(map(float, info.distortion)))

    @classmethod
    def from_toml(cls, path) -> PinholeCamera:
        """From a calibration file (``skycap camera calibrate --out camera.toml``): its ``[camera]`` table holds
        ``width_px``, ``height_px``, ``fx_px``, ``fy_px``, ``cx_px``, ``cy_px``, ``distortion_model`` ("none" or
        "plumb_bob") and ``distortion`` (k1, k2, p1, p2, k3); other tables (``[calibration]``: how it was made)
        are ignored here. A missing file or field is a :class:`CameraError` naming it."""
        import tomllib
        from pathlib import Path

        p = Path(path)
        if not p.is_file():
            raise CameraError(f"camera calibration file {p} not found; make one with 'skycap camera calibrate "
                              f"SOURCE --board charuco ... --out {p.name}' or fix camera.calibration_file")
        try:
            with p.open("rb") as f:
                t = tomllib.load(f).get("camera")
        except tomllib.TOMLDecodeError as e:
            raise CameraError(f"camera calibration file {p} is not valid TOML: {e}") from None
        need = ("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px")
        if not isinstance(t, dict) or any(k not in t for k in need):
            missing = [k for k in need if not isinstance(t, dict) or k not in t]
            raise CameraError(f"camera calibration file {p}: the [camera] table lacks {', '.join(missing)}")
        return cls(width_px=int(t["width_px"]), height_px=int(t["height_px"]), fx_px=float(t["fx_px"]),
                   fy_px=float(t["fy_px"]), cx_px=float(t["cx_px"]), cy_px=float(t["cy_px"]),
                   distortion_model=str(t.get("distortion_model", "none")),
                   distortion=tuple(float(x) for x in t.get("distortion", ())))

    # ------------------------------------------------------------------------------------- properties
    @property
    def K(self) -> np.ndarray:
        """(3, 3) camera matrix."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    @property
    def vfov_deg(self) -> float:
        return math.degrees(2 * math.atan(0.5 * self.height_px / self.fy_px))

    # ------------------------------------------------------------------------------------- projection
    def project_cam(self, p_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points (..., 3) -> (pixels (..., 2), depth z (...)); depth <= 0 is behind."""
        p_cam = np.asarray(p_cam, dtype=float)
        z = p_cam[..., 2]
        zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
        if self.distortion_model == "none":
            u = self.fx_px * p_cam[..., 0] / zs + self.cx_px
            v = self.fy_px * p_cam[..., 1] / zs + self.cy_px
            return np.stack([u, v], axis=-1), z
        x, y = p_cam[..., 0] / zs, p_cam[..., 1] / zs
        if self.distortion_model == "plumb_bob":
            k1, k2, p1, p2, k3 = self.distortion
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            x, y = (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                    y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)
        return np.stack([self.fx_px * x + self.cx_px, self.fy_px * y + self.cy_px], axis=-1), z

    def project(self, T_world_cam: np.ndarray, p_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (..., 3) -> (pixels (..., 2), depth (...))."""
        T_cw = invert_T(np.asarray(T_world_cam, dtype=float))
        p_cam = np.asarray(p_world, dtype=float) @ T_cw[:3, :3].T + T_cw[:3, 3]
        return self.project_cam(p_cam)

    def in_image(self, uv: np.ndarray) -> np.ndarray:
        """Whether pixels (..., 2) fall inside the image."""
        return (uv[..., 0] >= 0) & (uv[..., 0] < self.width_px) & (uv[..., 1] >= 0) & (uv[..., 1] < self.height_px)
