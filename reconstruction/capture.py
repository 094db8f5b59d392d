"""The capture: what every reconstruction method takes as input (the input contract).

A :class:`Capture` holds one :class:`CameraCapture` per camera (drone). Each camera has

* **poses** from the drone's own state estimate: ``t_pose_ns`` (P,), ``T_world_cam`` (P, 4, 4)
  (camera optical -> world NED, see :mod:`skycap.frames`), and their uncertainty as RMS 3D errors
  ``pos_sigma_m`` (P,) (sqrt of the position covariance's trace) and ``rot_sigma_deg`` (P,) (RMS
  rotation angle);
* optional **motion rates** at the same pose samples, from the drone's estimator and IMU: camera
  velocity ``vel_world_mps`` (P, 3) (world NED, m/s) with RMS 3D error ``vel_sigma_mps`` (P,), and
  camera angular velocity ``omega_cam_radps`` (P, 3) in the CAMERA frame (the rotation advances as
  R(t + dt) = R(t) exp([omega dt]x)) with RMS 3D error ``omega_sigma_radps`` (P,). Position and
  attitude samples are noisy but unbiased over time; rates are precise over seconds. ``None`` when the
  source has none (the fit then relies on the pose samples alone);
* **intrinsics**, timestamped: ``t_intrinsics_ns`` (I,), ``K`` (I, 3, 3) pinhole (no distortion),
  ``width_px``/``height_px``;
* **frames**: ``t_frame_ns`` (F,) capture times, 2D keypoints ``keypoints_px`` (F, D, 17, 2) in COCO-17
  order (:mod:`skycap.skeleton`) from D detectors (``detectors``, names), with confidences
  ``confidence`` (F, D, 17) in [0, 1] (0 = missing; the pixel value is then ignored), and optional
  ``image_paths`` (F,) (strings, may be empty).

Times are integer nanoseconds on one clock shared by all cameras (the recorder's); cameras need not be
synchronised: their frames can fall at any time. Poses and intrinsics are looked up at any time with
:meth:`CameraCapture.pose_at` (linear position + slerp rotation interpolation, clamped at the ends) and
:meth:`CameraCapture.K_at` (nearest earlier).

Sources: :func:`reconstruction.synth.synthesize_capture` (evaluation harness: real motion, virtual
drones) and the flight-folder reader :func:`reconstruction.multiview.flight.read_flight` (onboard
recorder MCAPs). A capture saves to / loads from one ``.npz`` (:meth:`Capture.save`, :meth:`Capture.load`).

Example::

    cap = Capture.load("capture.npz")
    cam = cap.cameras[0]
    T = cam.pose_at(cam.t_frame_ns)          # (F, 4, 4) drone-estimated camera poses at its frames
    uv = cam.keypoints_px[:, 0]              # (F, 17, 2) first detector
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from skycap.errors import SkycapError
from skycap.frames import make_T, project_points

__all__ = ["CaptureError", "CameraCapture", "Capture", "interpolate_poses"]

NUM_KEYPOINTS = 17


class CaptureError(SkycapError, ValueError):
    """A capture whose arrays do not fit the input contract."""


def interpolate_poses(t_src_ns: np.ndarray, T_src: np.ndarray, t_query_ns: np.ndarray) -> np.ndarray:
    """Rigid poses at query times: linear translation, slerp rotation, clamped to the source range.

    Shapes: t_src_ns (P,) increasing, T_src (P, 4, 4), t_query_ns (Q,) -> (Q, 4, 4).
    """
    t_src = np.asarray(t_src_ns, dtype=np.int64)
    tq = np.clip(np.asarray(t_query_ns, dtype=np.int64), t_src[0], t_src[-1])
    if len(t_src) == 1:
        return np.broadcast_to(T_src[0], (len(tq), 4, 4)).copy()
    ts = (t_src - t_src[0]).astype(float) * 1e-9
    tqs = (tq - t_src[0]).astype(float) * 1e-9
    R = Slerp(ts, Rotation.from_matrix(T_src[:, :3, :3]))(tqs).as_matrix()
    p = np.stack([np.interp(tqs, ts, T_src[:, k, 3]) for k in range(3)], axis=-1)
    return make_T(R, p)


@dataclasses.dataclass
class CameraCapture:
    """One camera's data; shapes in the module docstring. Validated on construction."""

    name: str
    t_pose_ns: np.ndarray  # (P,) int64
    T_world_cam: np.ndarray  # (P, 4, 4)
    pos_sigma_m: np.ndarray  # (P,)
    rot_sigma_deg: np.ndarray  # (P,)
    t_intrinsics_ns: np.ndarray  # (I,) int64
    K: np.ndarray  # (I, 3, 3)
    width_px: int
    height_px: int
    t_frame_ns: np.ndarray  # (F,) int64
    keypoints_px: np.ndarray  # (F, D, 17, 2)
    confidence: np.ndarray  # (F, D, 17)
    detectors: tuple[str, ...] = ("detector",)
    image_paths: tuple[str, ...] = ()
    vel_world_mps: np.ndarray | None = None  # (P, 3) world NED
    vel_sigma_mps: np.ndarray | None = None  # (P,) RMS 3D
    omega_cam_radps: np.ndarray | None = None  # (P, 3) camera frame
    omega_sigma_radps: np.ndarray | None = None  # (P,) RMS 3D

    def __post_init__(self) -> None:
        self.t_pose_ns = np.asarray(self.t_pose_ns, dtype=np.int64).reshape(-1)
        self.T_world_cam = np.asarray(self.T_world_cam, dtype=float)
        P = len(self.t_pose_ns)
        self.pos_sigma_m = np.broadcast_to(np.asarray(self.pos_sigma_m, dtype=float), (P,)).copy()
        self.rot_sigma_deg = np.broadcast_to(np.asarray(self.rot_sigma_deg, dtype=float), (P,)).copy()
        self.t_intrinsics_ns = np.asarray(self.t_intrinsics_ns, dtype=np.int64).reshape(-1)
        self.K = np.asarray(self.K, dtype=float)
        if self.K.ndim == 2:
            self.K = self.K[None]
        self.t_frame_ns = np.asarray(self.t_frame_ns, dtype=np.int64).reshape(-1)
        self.keypoints_px = np.asarray(self.keypoints_px, dtype=float)
        self.confidence = np.asarray(self.confidence, dtype=float)
        if self.keypoints_px.ndim == 3:  # (F, 17, 2): one detector
            self.keypoints_px = self.keypoints_px[:, None]
        if self.confidence.ndim == 2:
            self.confidence = self.confidence[:, None]
        self.detectors = tuple(self.detectors)
        self.image_paths = tuple(str(p) for p in self.image_paths)
        self.width_px = int(self.width_px)
        self.height_px = int(self.height_px)
        for rate, sigma in (("vel_world_mps", "vel_sigma_mps"), ("omega_cam_radps", "omega_sigma_radps")):
            if getattr(self, rate) is None:
                setattr(self, sigma, None)
                continue
            setattr(self, rate, np.asarray(getattr(self, rate), dtype=float))
            sig = 1.0 if getattr(self, sigma) is None else getattr(self, sigma)
            setattr(self, sigma, np.broadcast_to(np.asarray(sig, dtype=float), (P,)).copy())
        self._validate()

    @property
    def has_velocity(self) -> bool:
        return self.vel_world_mps is not None

    @property
    def has_angular_velocity(self) -> bool:
        return self.omega_cam_radps is not None

    def _validate(self) -> None:
        n = self.name
        P, F = len(self.t_pose_ns), len(self.t_frame_ns)
        if P == 0:
            raise CaptureError(f"camera {n!r} has no poses; the drone state topic must hold at least one pose")
        if self.T_world_cam.shape != (P, 4, 4):
            raise CaptureError(f"camera {n!r}: T_world_cam must be ({P}, 4, 4) like t_pose_ns, got {self.T_world_cam.shape}")
        if np.any(np.diff(self.t_pose_ns) <= 0):
            raise CaptureError(f"camera {n!r}: t_pose_ns must be strictly increasing; sort the poses and drop duplicates")
        I = len(self.t_intrinsics_ns)
        if I == 0 or self.K.shape != (I, 3, 3):
            raise CaptureError(f"camera {n!r}: K must be (I, 3, 3) with I = len(t_intrinsics_ns) >= 1, got {self.K.shape}, I={I}")
        if np.any(np.diff(self.t_intrinsics_ns) < 0):
            raise CaptureError(f"camera {n!r}: t_intrinsics_ns must be increasing")
        D = len(self.detectors)
        if self.keypoints_px.shape != (F, D, NUM_KEYPOINTS, 2):
            raise CaptureError(
                f"camera {n!r}: keypoints_px must be (F={F}, D={D}, 17, 2) (frames, detectors, COCO-17, uv), "
                f"got {self.keypoints_px.shape}"
            )
        if self.confidence.shape != (F, D, NUM_KEYPOINTS):
            raise CaptureError(f"camera {n!r}: confidence must be ({F}, {D}, 17), got {self.confidence.shape}")
        if np.any(np.diff(self.t_frame_ns) < 0):
            raise CaptureError(f"camera {n!r}: t_frame_ns must be increasing; sort the frames by capture time")
        if self.image_paths and len(self.image_paths) != F:
            raise CaptureError(f"camera {n!r}: image_paths has {len(self.image_paths)} entries for {F} frames")
        if not np.all(np.isfinite(self.T_world_cam)):
            raise CaptureError(f"camera {n!r}: T_world_cam holds NaN/inf")
        if self.width_px <= 0 or self.height_px <= 0:
            raise CaptureError(f"camera {n!r}: image size must be positive, got {self.width_px}x{self.height_px}")
        for rate, sigma, what in (("vel_world_mps", "vel_sigma_mps", "velocity"), ("omega_cam_radps", "omega_sigma_radps", "angular velocity")):
            v = getattr(self, rate)
            if v is None:
                continue
            if v.shape != (P, 3):
                raise CaptureError(f"camera {n!r}: {rate} must be ({P}, 3) like t_pose_ns (one {what} per pose sample), got {v.shape}")
            if not np.all(np.isfinite(v)):
                raise CaptureError(f"camera {n!r}: {rate} holds NaN/inf; drop those pose samples' rates (set {rate}=None) or repair them")
            if not np.all(getattr(self, sigma) > 0):
                raise CaptureError(f"camera {n!r}: {sigma} must be > 0 (the {what}'s RMS 3D error)")

    @property
    def num_frames(self) -> int:
        return len(self.t_frame_ns)

    @property
    def num_detectors(self) -> int:
        return len(self.detectors)

    def pose_at(self, t_ns: np.ndarray) -> np.ndarray:
        """Drone-estimated T_world_cam (Q, 4, 4) at times (Q,) (interpolated, clamped at the ends)."""
        return interpolate_poses(self.t_pose_ns, self.T_world_cam, np.atleast_1d(t_ns))

    def sigma_at(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(pos_sigma_m (Q,), rot_sigma_deg (Q,)) interpolated at times (Q,)."""
        t = np.atleast_1d(np.asarray(t_ns, dtype=np.int64)).astype(float)
        tp = self.t_pose_ns.astype(float)
        return np.interp(t, tp, self.pos_sigma_m), np.interp(t, tp, self.rot_sigma_deg)

    def K_at(self, t_ns: np.ndarray) -> np.ndarray:
        """Intrinsics (Q, 3, 3) valid at times (Q,): the latest at or before each time (else the first)."""
        t = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
        i = np.clip(np.searchsorted(self.t_intrinsics_ns, t, side="right") - 1, 0, len(self.t_intrinsics_ns) - 1)
        return self.K[i]

    def project(self, points_world: np.ndarray, frame: int, T_world_cam: np.ndarray | None = None) -> np.ndarray:
        """Pixels (..., 2) of world points (..., 3) at one frame, with the drone pose unless one is given."""
        t = self.t_frame_ns[frame]
        T = self.pose_at(t)[0] if T_world_cam is None else T_world_cam
        uv, _ = project_points(self.K_at(t)[0], T, points_world)
        return uv


@dataclasses.dataclass
class Capture:
    """All cameras of one flight (or one synthetic evaluation), plus free-form metadata."""

    cameras: list[CameraCapture]
    meta: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.cameras:
            raise CaptureError("a capture needs at least one camera")
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise CaptureError(f"camera names must be unique, got {names}")

    @property
    def num_cameras(self) -> int:
        return len(self.cameras)

    def time_range_ns(self) -> tuple[int, int]:
        """(first, last) frame time over all cameras."""
        ts = [c.t_frame_ns for c in self.cameras if c.num_frames]
        if not ts:
            raise CaptureError("the capture has no frames with keypoints")
        return int(min(t[0] for t in ts)), int(max(t[-1] for t in ts))

    def save(self, path: str | Path) -> Path:
        """Write one compressed ``.npz`` (loads back with :meth:`load`)."""
        import json

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays: dict[str, np.ndarray] = {"meta_json": np.array(json.dumps(self.meta, default=str))}
        for i, c in enumerate(self.cameras):
            for f in dataclasses.fields(c):
                v = getattr(c, f.name)
                if v is None:  # optional channel absent: no entry
                    continue
                arrays[f"cam{i}.{f.name}"] = np.array(v) if not isinstance(v, tuple) else np.array(list(v), dtype=str)
        arrays["num_cameras"] = np.array(len(self.cameras))
        np.savez_compressed(path, **arrays)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "Capture":
        import json

        path = Path(path)
        if not path.is_file():
            raise CaptureError(f"capture file {path} does not exist")
        z = np.load(path, allow_pickle=False)
        cams = []
        for i in range(int(z["num_cameras"])):
            kw = {}
            for f in dataclasses.fields(CameraCapture):
                if f"cam{i}.{f.name}" not in z.files:
                    if f.default is dataclasses.MISSING:
                        raise CaptureError(f"capture file {path} lacks cam{i}.{f.name}; it was not written by Capture.save")
                    continue
                v = z[f"cam{i}.{f.name}"]
                if f.name in ("detectors", "image_paths"):
                    kw[f.name] = tuple(str(s) for s in v.tolist())
                elif f.name == "name":
                    kw[f.name] = str(v)
                elif f.name in ("width_px", "height_px"):
                    kw[f.name] = int(v)
                else:
                    kw[f.name] = v
            cams.append(CameraCapture(**kw))
        return cls(cams, json.loads(str(z["meta_json"])))
