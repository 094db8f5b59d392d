"""The simulated camera: pinhole intrinsics, the mount (pitch gimbal or fixed), exact projections.

Pixel convention (as :mod:`shared_msgs.messages`): origin at the top-left pixel's *corner*, so pixel
(col, row) covers [col, col+1) x [row, row+1) and its centre is (col + 0.5, row + 0.5); the principal
point of a centred camera is (width/2, height/2).

    cam = PinholeCamera.from_config(CameraConfig())
    T_world_cam = camera_pose(cfg, position_ned_m, q_world_body_wxyz, gimbal_pitch_rad)
    gt = project_person(cam, T_world_cam, joints_ned_m)        # GtProjection: uv (17, 2), visibility, box
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from simulator.scene.body import PARTS, Ellipsoids, body_ellipsoids

PART_INDEX = {name: i for i, (name, _) in enumerate(PARTS)}
from simulator.scene.config import CameraConfig
from skycap.camera import PinholeCamera
from skycap.frames import R_from_quat_wxyz, T_world_cam_from_pose, invert_T

__all__ = [
    "PinholeCamera", "camera_pose", "GtProjection", "project_person", "ellipsoid_boxes",
    "joint_occlusion",
]  # fmt: skip


def camera_pose(
    cfg: CameraConfig,
    position_ned_m,
    q_world_body_wxyz,
    gimbal_pitch_rad: float | None = None,
    gimbal_yaw_rad: float | None = None,
) -> np.ndarray:
    """T_world_cam (4, 4) of the camera on a vehicle at ``position_ned_m`` with attitude ``q_world_body``.

    Gimbal mount: roll and pitch stabilised, camera yaw = vehicle yaw + ``gimbal_yaw_rad`` (the gimbal's yaw
    relative to the heading; None = 0), camera pitch = ``gimbal_pitch_rad`` (from the vehicle truth) or
    ``cfg.pitch_deg`` when None. Fixed mount: the camera turns with the body,
    pitched by ``cfg.pitch_deg`` relative to it. The lever arm turns with the body in both cases.
    """
    R_wb = R_from_quat_wxyz(q_world_body_wxyz)
    lever = np.asarray(cfg.lever_arm_body_m, dtype=float)
    if cfg.mount == "gimbal":
        yaw = math.atan2(R_wb[1, 0], R_wb[0, 0])
        c, s = math.cos(yaw), math.sin(yaw)
        R_yaw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        pitch = math.radians(cfg.pitch_deg) if gimbal_pitch_rad is None else float(gimbal_pitch_rad)
        position_cam = np.asarray(position_ned_m, dtype=float) + R_wb @ lever
        return T_world_cam_from_pose(position_cam, R_yaw, gimbal_pitch_rad=pitch,
                                     gimbal_yaw_rad=0.0 if gimbal_yaw_rad is None else float(gimbal_yaw_rad))
    return T_world_cam_from_pose(position_ned_m, R_wb, math.radians(cfg.pitch_deg), lever_arm_body_m=lever)


def ellipsoid_boxes(cam: PinholeCamera, ell_cam: Ellipsoids, near_m: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Exact image bounding boxes (E, 4) (x_min, y_min, x_max, y_max) of ellipsoids given in the camera
    frame, and a flag (E,) true where the ellipsoid lies wholly in front of ``near_m`` (else its box is
    meaningless). Uses the dual quadric: the outline's dual conic is ``K (B - c c^T) K^T``."""
    c = ell_cam.centers
    B = ell_cam.B
    front = c[:, 2] - np.sqrt(np.maximum(B[:, 2, 2], 0.0)) > near_m
    Q = B - c[:, :, None] * c[:, None, :]
    K = cam.K
    C = K @ Q @ K.T  # (E, 3, 3)
    out = np.zeros((len(c), 4))
    for ax in (0, 1):
        a, bb, cc = C[:, 2, 2], C[:, ax, 2], C[:, ax, ax]
        # tangent line x = s: cc - 2 s bb + s^2 a = 0
        disc = np.sqrt(np.maximum(bb * bb - a * cc, 0.0))
        a_s = np.where(np.abs(a) < 1e-12, 1e-12, a)
        s1, s2 = (bb - disc) / a_s, (bb + disc) / a_s
        out[:, ax] = np.minimum(s1, s2)
        out[:, ax + 2] = np.maximum(s1, s2)
    return out, front


@dataclasses.dataclass
class GtProjection:
    """Exact projections of the person into one camera.

    uv_px: (17, 2) joint pixels; depth_m: (17,) camera z; in_front: (17,) depth > 0.05 m;
    in_image: (17,) pixel inside the image; visible: (17,) both; occluded: (17,) hidden behind another
    body part (see :func:`joint_occlusion`; a visible joint may be occluded, detectors still guess it);
    box_px: (4,) body box (x_min, y_min, x_max, y_max) from the projected body ellipsoids, clipped to
    the image, or None when no part of the body is in front of the camera and in the image;
    box_unclipped_px: the same before clipping; truncated: the box was clipped.
    """

    uv_px: np.ndarray
    depth_m: np.ndarray
    in_front: np.ndarray
    in_image: np.ndarray
    visible: np.ndarray
    box_px: np.ndarray | None
    box_unclipped_px: np.ndarray | None
    truncated: bool
    occluded: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.occluded is None:
            self.occluded = np.zeros(len(self.visible), bool)


#: Face keypoints lie on the head's surface: the head ellipsoid can hide them (the back of the head).
_FACE = (0, 1, 2, 3, 4)


def joint_occlusion(p_cam: np.ndarray, ell_cam: Ellipsoids, margin_m: float = 0.03, face_margin_m: float = 0.06) -> np.ndarray:
    """(J,) True where the camera's ray to a joint (camera frame (J, 3)) enters another body part more
    than ``margin_m`` before the joint. Parts containing the joint (its own limb segments) do not count,
    except the head for the face keypoints (``face_margin_m``): a nose seen from behind is occluded."""
    z = p_cam[:, 2]
    d = p_cam / np.where(np.abs(z) < 1e-9, 1e-9, z)[:, None]  # rays with z = 1
    G = np.swapaxes(ell_cam.M, 1, 2) @ ell_cam.M  # (E, 3, 3)
    c = ell_cam.centers
    Gd = np.einsum("eij,pj->pei", G, d)  # (J, E, 3)
    a = np.einsum("pei,pi->pe", Gd, d)
    b = np.einsum("pei,ei->pe", Gd, c)
    cc = np.einsum("ei,eij,ej->e", c, G, c)[None, :] - 1.0
    disc = b * b - a * cc
    with np.errstate(invalid="ignore"):
        s_in = (b - np.sqrt(disc)) / a
    rel = p_cam[:, None, :] - c[None, :, :]
    q = np.einsum("pei,eij,pej->pe", rel, G, rel)  # < 1 inside
    contains = q <= 1.2**2
    margin = np.full(a.shape, margin_m)
    face = np.zeros(len(p_cam), bool)
    face[list(_FACE)[: len(p_cam)]] = True
    head = np.zeros(a.shape[1], bool)
    head[[PART_INDEX["head"], PART_INDEX["hair"]]] = True
    exclude = contains & ~(face[:, None] & head[None, :])
    margin[face[:, None] & head[None, :] & contains] = face_margin_m
    hits = (disc > 0) & ~exclude & (s_in < z[:, None] - margin) & (s_in > 0)
    return hits.any(axis=1) & (z > 0)


def project_person(
    cam: PinholeCamera, T_world_cam: np.ndarray, joints_ned_m: np.ndarray, ellipsoids: Ellipsoids | None = None
) -> GtProjection:
    """Ground-truth projections of COCO-17 joints (17, 3) and the body box (from its ellipsoids)."""
    T_cw = invert_T(np.asarray(T_world_cam, dtype=float))
    R_cw, t_cw = T_cw[:3, :3], T_cw[:3, 3]
    p_cam = np.asarray(joints_ned_m, dtype=float) @ R_cw.T + t_cw
    uv, z = cam.project_cam(p_cam)
    in_front = z > 0.05
    in_img = cam.in_image(uv) & in_front
    ell = (ellipsoids if ellipsoids is not None else body_ellipsoids(joints_ned_m)).transformed(R_cw, t_cw)
    boxes, front = ellipsoid_boxes(cam, ell)
    box = box_c = None
    truncated = False
    if front.any():
        b = boxes[front]
        box_c = np.array([b[:, 0].min(), b[:, 1].min(), b[:, 2].max(), b[:, 3].max()])
        clipped = np.array(
            [max(box_c[0], 0.0), max(box_c[1], 0.0), min(box_c[2], cam.width_px), min(box_c[3], cam.height_px)]
        )
        if clipped[2] > clipped[0] and clipped[3] > clipped[1]:
            box = clipped
            truncated = bool(np.any(np.abs(clipped - box_c) > 1e-9))
    occluded = joint_occlusion(p_cam, ell)
    return GtProjection(uv, z, in_front, in_img, in_img.copy(), box, box_c, truncated, occluded)
