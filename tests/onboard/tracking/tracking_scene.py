"""Small scene generator for the tracking tests: drones around a walking person, boxes with pixel noise."""

from __future__ import annotations

import math

import numpy as np

from onboard.tracking.measurement import box_from_person, measurement_from_box
from skycap.camera import PinholeCamera
from shared_msgs.messages import BoundingBox, CameraInfo, Detections
from skycap.frames import R_world_body_from_euler, T_world_cam_from_pose

CAM = PinholeCamera(fx_px=1000.0, fy_px=1000.0, cx_px=960.0, cy_px=540.0, width_px=1920, height_px=1080)
PERSON_HALF_H = 0.845


def look_at_pose(cam_ned: np.ndarray, target_ned: np.ndarray) -> np.ndarray:
    """T_world_cam of a gimballed camera at cam_ned looking at target_ned (zero roll)."""
    d = np.asarray(target_ned, float) - np.asarray(cam_ned, float)
    yaw = math.atan2(d[1], d[0])
    pitch = -math.atan2(d[2], math.hypot(d[0], d[1]))  # negative = down
    return T_world_cam_from_pose(cam_ned, R_world_body_from_euler(0.0, 0.0, yaw), gimbal_pitch_rad=pitch)


def person_center(t_s: float) -> np.ndarray:
    """Walking 1.2 m/s north-east with a gentle turn; centre of mass at down = -0.845 (ground at 0)."""
    return np.array([1.0 * t_s, 0.6 * t_s + 2.0 * math.sin(0.2 * t_s), -PERSON_HALF_H])


def drone_positions(t_s: float, n: int = 3, radius_m: float = 8.0, altitude_m: float = 8.0) -> np.ndarray:
    c = person_center(t_s)
    out = []
    for k in range(n):
        a = 2 * math.pi * k / n + 0.05 * t_s
        out.append([c[0] + radius_m * math.cos(a), c[1] + radius_m * math.sin(a), -altitude_m])
    return np.array(out)


def simulate(
    duration_s: float,
    rng: np.random.Generator,
    n: int = 3,
    rate_hz: float = 4.0,
    px_sigma: float = 2.0,
    offsets: dict[int, np.ndarray] | None = None,
    pos_var_m2: float | dict[int, float] = 0.25,
):
    """Measurements (time-ordered) from n drones ("drone_0".."drone_{n-1}"), detections staggered in time.

    offsets: per drone index, its constant GPS offset (reported = true + offset); pos_var_m2: the camera
    position variance each drone reports (one value, or per drone index; default 0.25)."""
    offsets = offsets or {}
    out = []
    period = 1.0 / rate_hz
    for k in range(n):
        t = 0.05 + k * period / n
        while t < duration_s:
            cam_true = drone_positions(t, n)[k]
            p = person_center(t)
            T_true = look_at_pose(cam_true, p)
            box, _ = box_from_person(p, CAM, T_true)
            box = box + rng.normal(0, px_sigma, 4)
            T_rep = T_true.copy()
            T_rep[:3, 3] += offsets.get(k, np.zeros(3))
            pv = pos_var_m2.get(k, 0.25) if isinstance(pos_var_m2, dict) else pos_var_m2
            cov = np.diag([pv] * 3 + [1e-5] * 3)
            m = measurement_from_box(box, CAM, T_rep, cov, t_ns=int(t * 1e9), source_id=f"drone_{k}", edge_var_px2=np.full(4, px_sigma**2))
            out.append(m)
            t += period
    out.sort(key=lambda m: m.t_ns)
    return out


def camera_info() -> CameraInfo:
    """The scene camera (:data:`CAM`) as drone_0's CameraInfo message."""
    return CameraInfo(header=CameraInfo.make_header("drone_0", 0), camera_id="cam", width_px=CAM.width_px,
                      height_px=CAM.height_px, fx_px=CAM.fx_px, fy_px=CAM.fy_px, cx_px=CAM.cx_px, cy_px=CAM.cy_px)


def detections_message(k: int, t_s: float, frame: int, rng: np.random.Generator, offset=np.zeros(3), px_sigma: float = 2.0,
                       pos_var_m2: float = 0.25) -> tuple[Detections, np.ndarray]:
    """(drone k's Detections of the walking person at t_s, the exact box). The box has pixel noise px_sigma;
    the reported camera position is true + offset, with position variance pos_var_m2 in T_world_cam_cov."""
    p = person_center(t_s)
    T_true = look_at_pose(drone_positions(t_s, 3)[k], p)
    box_true, _ = box_from_person(p, CAM, T_true)
    box = box_true + rng.normal(0, px_sigma, 4)
    T_rep = T_true.copy()
    T_rep[:3, 3] += offset
    v = px_sigma**2
    det = Detections(
        header=Detections.make_header(f"drone_{k}", int(t_s * 1e9), frame), camera_id="cam", frame_index=frame,
        detector="simulated", mode="simulated",
        boxes=[BoundingBox(x_min_px=box[0], y_min_px=box[1], x_max_px=box[2], y_max_px=box[3], score=0.9,
                           var_x_min_px2=v, var_y_min_px2=v, var_x_max_px2=v, var_y_max_px2=v)],
        width_px=CAM.width_px, height_px=CAM.height_px, T_world_cam=tuple(T_rep.reshape(-1)),
        T_world_cam_cov=tuple(np.diag([pos_var_m2] * 3 + [1e-5] * 3).reshape(-1)))
    return det, box_true
