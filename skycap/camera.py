"""The one camera model: pinhole intrinsics with optional OpenCV distortion, posed by ``T_world_cam``.

    from skycap.camera import PinholeCamera

    cam = PinholeCamera.from_fov(width_px=960, height_px=540, hfov_deg=70.0)
    cam = PinholeCamera.from_camera_info(info)          # the CameraInfo message a drone publishes
    cam = PinholeCamera.from_toml("camera.toml")        # a calibration file (``skycap camera calibrate``)
    cam.to_toml("camera.toml", calibration={...})       # ... and writing one
    uv, depth_m = cam.project(T_world_cam, points_world_ned_m)   # (..., 2) pixels, (...,) depth along +z

Frames (:mod:`skycap.frames`): camera = OpenCV optical (x right, y down, z forward); ``T_world_cam`` maps
camera coordinates to world NED. Used by the simulator's renderer and camera node, the onboard tracking
measurement model and the offline track refinement; the ``CameraInfo`` message is its wire form.

Distortion: ``"none"`` or ``"plumb_bob"`` (OpenCV's radial-tangential ``(k1, k2, p1, p2, k3)``), applied by
:meth:`PinholeCamera.project_cam` to normalised coordinates as ``cv2.projectPoints`` does, and inverted (numpy
Newton iterations, no OpenCV in the core) by :meth:`PinholeCamera.undistort_points` /
:meth:`PinholeCamera.undistort_normalized`.
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

    def to_toml(self, path, *, calibration: dict | None = None, overwrite: bool = False) -> None:
        """Write the calibration file :meth:`from_toml` reads: the ``[camera]`` table and, when given, a
        ``[calibration]`` table saying how it was made (``rms_reprojection_px``, ``views_used``, ``views_rejected``,
        board, image size, ``created_utc``, ``source``...; ``None`` values are left out). An existing file is a
        :class:`CameraError` unless ``overwrite`` (the CLI's ``--force``)."""
        from pathlib import Path

        import tomli_w

        p = Path(path)
        if p.exists() and not overwrite:
            raise CameraError(f"{p} exists; pass --force (overwrite=True) to replace it, or choose another --out")
        doc: dict = {"camera": {
            "width_px": int(self.width_px), "height_px": int(self.height_px), "fx_px": float(self.fx_px),
            "fy_px": float(self.fy_px), "cx_px": float(self.cx_px), "cy_px": float(self.cy_px),
            "distortion_model": self.distortion_model, "distortion": [float(x) for x in self.distortion],
        }}  # fmt: skip
        if calibration:
            doc["calibration"] = _toml_clean(calibration)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(tomli_w.dumps(doc))

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
            x, y = _plumb_bob(x, y, self.distortion)
        return np.stack([self.fx_px * x + self.cx_px, self.fy_px * y + self.cy_px], axis=-1), z

    def undistort_normalized(self, uv_px: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Distorted pixels (..., 2) -> undistorted normalised coordinates (x/z, y/z) (..., 2): the rays
        :meth:`project_cam` maps onto those pixels (Newton iterations on the plumb_bob model; exact for "none").
        Points where the lens model folds back (far outside the calibrated field) may not converge."""
        uv = np.asarray(uv_px, dtype=float)
        xd = (uv[..., 0] - self.cx_px) / self.fx_px
        yd = (uv[..., 1] - self.cy_px) / self.fy_px
        if self.distortion_model == "none":
            return np.stack([xd, yd], axis=-1)
        x, y = xd.copy(), yd.copy()
        for _ in range(iterations):
            (fx, fy), (a, b, c, d) = _plumb_bob(x, y, self.distortion, jacobian=True)
            ex, ey = xd - fx, yd - fy
            det = a * d - b * c
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            dx, dy = (d * ex - b * ey) / det, (a * ey - c * ex) / det
            x, y = x + dx, y + dy
            if np.all(np.abs(dx) + np.abs(dy) < 1e-12):
                break
        return np.stack([x, y], axis=-1)

    def undistort_points(self, uv_px: np.ndarray) -> np.ndarray:
        """Distorted pixels (..., 2) -> the ideal pinhole pixels of the same ``K`` (what ``cv2.undistortPoints``
        with ``P=K`` gives): where the same rays land without the lens distortion."""
        xy = self.undistort_normalized(uv_px)
        return np.stack([self.fx_px * xy[..., 0] + self.cx_px, self.fy_px * xy[..., 1] + self.cy_px], axis=-1)

    def project(self, T_world_cam: np.ndarray, p_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (..., 3) -> (pixels (..., 2), depth (...))."""
        T_cw = invert_T(np.asarray(T_world_cam, dtype=float))
        p_cam = np.asarray(p_world, dtype=float) @ T_cw[:3, :3].T + T_cw[:3, 3]
        return self.project_cam(p_cam)

    def in_image(self, uv: np.ndarray) -> np.ndarray:
        """Whether pixels (..., 2) fall inside the image."""
        return (uv[..., 0] >= 0) & (uv[..., 0] < self.width_px) & (uv[..., 1] >= 0) & (uv[..., 1] < self.height_px)


def _plumb_bob(x: np.ndarray, y: np.ndarray, dist: tuple[float, ...], jacobian: bool = False):
    """OpenCV's radial-tangential distortion of normalised coordinates; with ``jacobian`` also
    (dxd/dx, dxd/dy, dyd/dx, dyd/dy)."""
    k1, k2, p1, p2, k3 = dist
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    if not jacobian:
        return xd, yd
    dr = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
    cross = 2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y
    return (xd, yd), (radial + 2.0 * x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x, cross,
                      cross, radial + 2.0 * y * y * dr + 6.0 * p1 * y + 2.0 * p2 * x)


def _toml_clean(v):
    """A value TOML can hold: None dropped from tables, tuples as lists, numpy scalars as Python numbers."""
    if isinstance(v, dict):
        return {str(k): _toml_clean(x) for k, x in v.items() if x is not None}
    if isinstance(v, (list, tuple)):
        return [_toml_clean(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return _toml_clean(v.tolist())
    return v
