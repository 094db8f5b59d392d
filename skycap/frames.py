"""Frames, rotations and camera poses: the one place where conventions are defined and converted.

Conventions used across skycap (say them once, convert here):

* **World frame** = local **NED** (north_m, east_m, down_m) about the flight's origin (the simulator's
  origin, or the home position of the first drone on a real flight). Gravity points along +down.
  Geodetic <-> NED uses a local tangent plane at ``origin`` (:func:`geodetic_to_ned`).
* **Body frame** = FRD (x forward, y right, z down), as PX4/MAVLink. ``R_world_body`` maps body
  vectors to NED; from MAVLink attitude (roll, pitch, yaw) by :func:`R_world_body_from_euler`.
* **Camera frame** = OpenCV optical (x right, y down, z forward out of the lens).
  ``T_world_cam`` (4x4) maps camera coordinates to world (NED) coordinates;
  pixel = K @ (R_cam_world @ p_world + t_cam_world) / z.
* **Mocap / output frame**: BVH files are Y-up right-handed (the CMU input after its own root
  rotation, in centimetres, and every skycap export); conversions are :func:`yup_to_ned` /
  :func:`ned_to_yup` (north = x, up = y, east = z).
* Angles in radians unless the name ends in ``_deg``; yaw is about +down, 0 = north, positive = east.
"""

from __future__ import annotations

import math

import numpy as np


def _rotation():
    """scipy's Rotation, imported on first use: importing scipy.spatial costs ~0.5 s, and the agent's start
    (a restart after a crash is recording time lost) needs none of it before it flies."""
    from scipy.spatial.transform import Rotation

    return Rotation

EARTH_RADIUS_M = 6378137.0

# Camera optical axes expressed in the body FRD frame for a camera looking straight forward:
# cam x (right) = body y, cam y (down) = body z, cam z (forward) = body x.
R_BODY_CAM_FORWARD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])

# NED -> Y-up right-handed (x = north, y = up, z = east): x = n, y = -d, z = e.
R_YUP_NED = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from rotation (...,3,3) and translation (...,3)."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transform(s) (...,4,4)."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    return make_T(Rt, -np.einsum("...ij,...j->...i", Rt, t))


def R_world_body_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """Body FRD -> NED rotation from aerospace Euler angles (yaw-pitch-roll, intrinsic ZYX)."""
    return _rotation().from_euler("ZYX", [yaw_rad, pitch_rad, roll_rad]).as_matrix()


def euler_from_R_world_body(R: np.ndarray) -> tuple[float, float, float]:
    """(roll_rad, pitch_rad, yaw_rad) of a body FRD -> NED rotation."""
    yaw, pitch, roll = _rotation().from_matrix(R).as_euler("ZYX")
    return float(roll), float(pitch), float(yaw)


def R_body_cam(gimbal_pitch_rad: float = 0.0, gimbal_yaw_rad: float = 0.0) -> np.ndarray:
    """Camera optical frame -> body FRD for a camera (or gimbal) pitched and yawed relative to the body.

    ``gimbal_pitch_rad`` < 0 tilts the camera down (MAVLink gimbal convention), yaw > 0 turns it right.
    """
    R_gimbal = _rotation().from_euler("ZY", [gimbal_yaw_rad, gimbal_pitch_rad]).as_matrix()
    return R_gimbal @ R_BODY_CAM_FORWARD


def T_world_cam_from_pose(
    position_ned_m: np.ndarray,
    R_world_body: np.ndarray,
    gimbal_pitch_rad: float = 0.0,
    gimbal_yaw_rad: float = 0.0,
    lever_arm_body_m: np.ndarray | None = None,
) -> np.ndarray:
    """Camera pose in the world (NED) from the vehicle pose and the camera mount.

    For a gimbal that stabilises roll and pitch, pass ``R_world_body`` built from yaw alone.
    """
    R_wc = np.asarray(R_world_body) @ R_body_cam(gimbal_pitch_rad, gimbal_yaw_rad)
    t = np.asarray(position_ned_m, dtype=float)
    if lever_arm_body_m is not None:
        t = t + np.asarray(R_world_body) @ np.asarray(lever_arm_body_m, dtype=float)
    return make_T(R_wc, t)


def T_world_cam_mount(
    position_ned_m,
    q_world_body_wxyz,
    mount: str,
    pitch_rad: float,
    yaw_rad: float = 0.0,
    lever_arm_body_m=None,
) -> np.ndarray:
    """T_world_cam (4, 4) of a camera on a vehicle at ``position_ned_m`` (NED) with attitude ``q_world_body``.

    ``mount="gimbal"``: roll and pitch stabilised; the camera's yaw = the vehicle's heading + ``yaw_rad`` and its
    pitch relative to the horizon = ``pitch_rad`` (negative = down; the gimbal's reported or commanded angles).
    ``mount="fixed"``: the camera turns with the body, pitched by ``pitch_rad`` and yawed by ``yaw_rad`` relative
    to it. The lever arm (camera centre in body FRD, m) turns with the body in both cases.
    """
    R_wb = R_from_quat_wxyz(q_world_body_wxyz)
    lever = np.zeros(3) if lever_arm_body_m is None else np.asarray(lever_arm_body_m, dtype=float)
    position = np.asarray(position_ned_m, dtype=float) + R_wb @ lever
    if mount == "gimbal":
        yaw = math.atan2(R_wb[1, 0], R_wb[0, 0])
        c, s = math.cos(yaw), math.sin(yaw)
        R_yaw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return T_world_cam_from_pose(position, R_yaw, gimbal_pitch_rad=pitch_rad, gimbal_yaw_rad=yaw_rad)
    if mount == "fixed":
        return T_world_cam_from_pose(position, R_wb, gimbal_pitch_rad=pitch_rad, gimbal_yaw_rad=yaw_rad)
    raise ValueError(f"camera mount {mount!r}: use 'gimbal' or 'fixed'")


def project_points(K: np.ndarray, T_world_cam: np.ndarray, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection (no distortion) of world points (...,3) -> (pixels (...,2), depth_m (...)).

    Points behind the camera get depth <= 0; their pixels are meaningless.
    """
    T_cw = invert_T(T_world_cam)
    p_cam = np.einsum("ij,...j->...i", T_cw[:3, :3], points_world) + T_cw[:3, 3]
    z = p_cam[..., 2]
    zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
    uv = np.einsum("ij,...j->...i", K[:2, :2], p_cam[..., :2] / zs[..., None]) + K[:2, 2]
    return uv, z


def intrinsics_matrix(fx_px: float, fy_px: float, cx_px: float, cy_px: float) -> np.ndarray:
    return np.array([[fx_px, 0.0, cx_px], [0.0, fy_px, cy_px], [0.0, 0.0, 1.0]])


def yup_to_ned(points_yup: np.ndarray) -> np.ndarray:
    """Y-up right-handed (x, y, z) -> NED (north = x, east = z, down = -y); inverse of :func:`ned_to_yup`."""
    return np.asarray(points_yup) @ R_YUP_NED


def ned_to_yup(points_ned: np.ndarray) -> np.ndarray:
    """NED -> Y-up right-handed (north, up, east); used for BVH and viewer exports."""
    return np.asarray(points_ned) @ R_YUP_NED.T


def ned_to_enu(v: np.ndarray) -> np.ndarray:
    """NED (n, e, d) -> ENU (e, n, -d)."""
    v = np.asarray(v, dtype=float)
    return np.stack([v[..., 1], v[..., 0], -v[..., 2]], axis=-1)


def enu_to_ned(v: np.ndarray) -> np.ndarray:
    """ENU (e, n, u) -> NED (n, e, -u)."""
    v = np.asarray(v, dtype=float)
    return np.stack([v[..., 1], v[..., 0], -v[..., 2]], axis=-1)


def geodetic_to_ned(lat_deg, lon_deg, alt_m, origin_lat_deg: float, origin_lon_deg: float, origin_alt_m: float) -> np.ndarray:
    """Geodetic (WGS-84 lat/lon, altitude AMSL) -> local NED about an origin (equirectangular, < 1 cm at 1 km)."""
    lat0 = np.radians(origin_lat_deg)
    n = np.radians(np.asarray(lat_deg) - origin_lat_deg) * EARTH_RADIUS_M
    e = np.radians(np.asarray(lon_deg) - origin_lon_deg) * EARTH_RADIUS_M * np.cos(lat0)
    d = origin_alt_m - np.asarray(alt_m)
    return np.stack(np.broadcast_arrays(n, e, d), axis=-1).astype(float)


def ned_to_geodetic(ned_m, origin_lat_deg: float, origin_lon_deg: float, origin_alt_m: float) -> tuple:
    """Inverse of :func:`geodetic_to_ned`: (lat_deg, lon_deg, alt_m)."""
    ned_m = np.asarray(ned_m, dtype=float)
    lat0 = np.radians(origin_lat_deg)
    lat = origin_lat_deg + np.degrees(ned_m[..., 0] / EARTH_RADIUS_M)
    lon = origin_lon_deg + np.degrees(ned_m[..., 1] / (EARTH_RADIUS_M * np.cos(lat0)))
    alt = origin_alt_m - ned_m[..., 2]
    return lat, lon, alt


def wrap_angle_rad(a):
    """Wrap to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


# ------------------------------------------------------------- quaternions (w, x, y, z), no scipy (hot paths)
def yaw_from_R(R: np.ndarray) -> float:
    """Heading (rad, 0 = north, + = east) of a body FRD -> NED rotation matrix."""
    return math.atan2(R[1, 0], R[0, 0])


def euler_from_R(R: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) rad of R_world_body (ZYX), without scipy (hot path)."""
    return (
        math.atan2(R[2, 1], R[2, 2]),
        -math.asin(max(-1.0, min(1.0, R[2, 0]))),
        math.atan2(R[1, 0], R[0, 0]),
    )


def quat_wxyz_from_R(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method)."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        return 0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s
    if R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        return (R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s
    if R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        return (R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s
    s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
    return (R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s


def R_from_quat_wxyz(q) -> np.ndarray:
    """Body FRD -> NED rotation from a (w, x, y, z) quaternion (the messages' order), normalised first."""
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z) or 1.0
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def yaw_from_quat_wxyz(q_wxyz) -> float:
    """Heading (rad, 0 = north, + = east) of a body FRD -> NED quaternion (w, x, y, z)."""
    w, x, y, z = q_wxyz
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
