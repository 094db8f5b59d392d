"""The ground station's 3D view maths, plain numpy (no Qt): an orbiting look-at camera in the NED world frame and
a pinhole projection onto a widget's pixels.

    pos_ned, R = orbit_camera(target_ned=(0, 0, -1), azimuth_rad=0.6, elevation_rad=0.4, distance_m=20)
    uv_px = project(ned_to_view(points_ned, pos_ned, R), width_px=800, height_px=600, vfov_rad=math.radians(50))

Conventions: world NED metres (north, east, down; altitude = -down). The camera sits at ``target + distance *
(cos(el) cos(az), cos(el) sin(az), -sin(el))``: azimuth is the bearing from the target to the camera (0 = the camera
north of the target, looking south; pi/2 = east of it), elevation above the horizon. View frame: x right, y down
in the image, z forward (depth, metres). Pixels: u right, v down, the principal point at the widget's centre.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["orbit_camera", "ned_to_view", "project", "project_ned", "ground_grid", "circle_ned",
           "frustum_segments", "bone_side", "LEFT", "RIGHT", "CENTRE"]

LEFT, RIGHT, CENTRE = "left", "right", "centre"
_DOWN = np.array([0.0, 0.0, 1.0])


def orbit_camera(target_ned, azimuth_rad: float, elevation_rad: float, distance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(camera position NED (3,), R_view_from_ned (3, 3)) of a camera ``distance_m`` from ``target_ned`` looking at
    it; rows of R: the image's right, the image's down, forward. Elevation is kept inside (-89.9, 89.9) deg so that
    "up" stays defined."""
    if not distance_m > 0:
        raise ValueError(f"distance_m = {distance_m}: the camera's distance to its target must be positive")
    el = float(np.clip(elevation_rad, -math.radians(89.9), math.radians(89.9)))
    t = np.asarray(target_ned, dtype=float).reshape(3)
    offset = distance_m * np.array([math.cos(el) * math.cos(azimuth_rad), math.cos(el) * math.sin(azimuth_rad),
                                    -math.sin(el)])
    pos = t + offset
    fwd = -offset / np.linalg.norm(offset)
    right = np.cross(_DOWN, fwd)
    right /= np.linalg.norm(right)
    down_img = np.cross(fwd, right)
    return pos, np.stack([right, down_img, fwd])


def ned_to_view(points_ned, camera_pos_ned, R_view_from_ned) -> np.ndarray:
    """(N, 3) NED points -> (N, 3) view-frame points (x right, y down, z depth), metres."""
    p = np.asarray(points_ned, dtype=float).reshape(-1, 3)
    return (p - np.asarray(camera_pos_ned, dtype=float)) @ np.asarray(R_view_from_ned, dtype=float).T


def focal_px(height_px: float, vfov_rad: float) -> float:
    return 0.5 * height_px / math.tan(0.5 * vfov_rad)


def project(points_view, width_px: float, height_px: float, vfov_rad: float, near_m: float = 0.1) -> np.ndarray:
    """(N, 3) view-frame points -> (N, 2) pixels (u right, v down); NaN for points closer than ``near_m`` in depth
    (behind the camera)."""
    p = np.asarray(points_view, dtype=float).reshape(-1, 3)
    f = focal_px(height_px, vfov_rad)
    out = np.full((len(p), 2), np.nan)
    ok = p[:, 2] >= near_m
    out[ok, 0] = 0.5 * width_px + f * p[ok, 0] / p[ok, 2]
    out[ok, 1] = 0.5 * height_px + f * p[ok, 1] / p[ok, 2]
    return out


def project_ned(points_ned, camera_pos_ned, R_view_from_ned, width_px: float, height_px: float,
                vfov_rad: float) -> np.ndarray:
    """NED points straight to pixels (NaN behind the camera)."""
    return project(ned_to_view(points_ned, camera_pos_ned, R_view_from_ned), width_px, height_px, vfov_rad)


def ground_grid(center_north_m: float, center_east_m: float, half_m: float, step_m: float) -> np.ndarray:
    """(K, 2, 3) NED line segments of a square grid on the ground (down = 0) around the centre, on multiples of
    ``step_m``."""
    n0 = math.floor((center_north_m - half_m) / step_m) * step_m
    e0 = math.floor((center_east_m - half_m) / step_m) * step_m
    k = int(math.ceil(2 * half_m / step_m)) + 1
    ns = n0 + step_m * np.arange(k + 1)
    es = e0 + step_m * np.arange(k + 1)
    segs = [((n, es[0], 0.0), (n, es[-1], 0.0)) for n in ns] + [((ns[0], e, 0.0), (ns[-1], e, 0.0)) for e in es]
    return np.asarray(segs, dtype=float)


def circle_ned(center_north_m: float, center_east_m: float, down_m: float, radius_m: float, n: int = 64) -> np.ndarray:
    """(n + 1, 3) closed horizontal circle in NED."""
    a = np.linspace(0.0, 2 * math.pi, n + 1)
    return np.stack([center_north_m + radius_m * np.cos(a), center_east_m + radius_m * np.sin(a),
                     np.full(n + 1, float(down_m))], axis=1)


def frustum_segments(pos_ned, yaw_rad: float, depression_rad: float, hfov_rad: float, vfov_rad: float,
                     length_m: float) -> np.ndarray:
    """(8, 2, 3) NED segments of a camera frustum at ``pos_ned`` looking along ``yaw_rad`` (from north, towards
    east) and ``depression_rad`` below the horizon: 4 edges from the apex and the far rectangle."""
    pos = np.asarray(pos_ned, dtype=float)
    corners = []
    for dv, dh in ((-1, -1), (-1, 1), (1, 1), (1, -1)):
        dep = depression_rad + dv * vfov_rad / 2
        brg = yaw_rad + dh * hfov_rad / 2
        corners.append(pos + length_m * np.array([math.cos(dep) * math.cos(brg), math.cos(dep) * math.sin(brg),
                                                  math.sin(dep)]))
    segs = [(pos, c) for c in corners] + [(corners[i], corners[(i + 1) % 4]) for i in range(4)]
    return np.asarray(segs, dtype=float)


def bone_side(names: tuple[str, ...] | list[str], a: int, b: int) -> str:
    """LEFT if both ends are the person's left joints, RIGHT if both right, else CENTRE (torso cross bars, face)."""
    sa = "left" if names[a].startswith("left") else "right" if names[a].startswith("right") else ""
    sb = "left" if names[b].startswith("left") else "right" if names[b].startswith("right") else ""
    if sa and sa == sb:
        return LEFT if sa == "left" else RIGHT
    return CENTRE
