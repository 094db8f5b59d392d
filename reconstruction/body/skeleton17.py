"""The COCO-17 kinematic skeleton: a tree of 21 nodes whose positions include the 17 COCO keypoints, its
rest geometry from a 16-number shape vector, forward kinematics (numpy and torch) and the inverse:
local joint rotations that reproduce given COCO-17 positions (used by the BVH exporter and to turn
motion capture into training poses for the prior).

Rest frame ("body frame"): x = the person's left, y = up, z = forward (right-handed), T-pose: legs
straight down (-y), arms straight out (left arm +x, right arm -x).

Nodes (index name <- parent)::

     0 pelvis (root; mid-hip)            7 spine   <- 0 (zero offset, turns the trunk)
     1 l_hip   <- 0   2 l_knee <- 1       8 neck    <- 7 (mid-shoulder)
     3 l_ankle <- 2                       9 l_shoulder <- 8  10 l_elbow <- 9  11 l_wrist <- 10
     4 r_hip   <- 0   5 r_knee <- 4       12 r_shoulder <- 8 13 r_elbow <- 12 14 r_wrist <- 13
     6 r_ankle <- 5                       15 head <- 8 (zero offset)  16 nose 17 l_eye 18 r_eye
                                          19 l_ear 20 r_ear (all <- 15)

Rotating joints (:data:`POSE_JOINTS`, 11, in this order): l_hip, l_knee, r_hip, r_knee, spine, neck,
l_shoulder, l_elbow, r_shoulder, r_elbow, head; plus the root orientation. Ankles, wrists and face
points are leaves.

Shape vector (16, metres), left/right symmetric (:data:`SHAPE_NAMES`)::

    hip_x (half hip width; pelvis = mid-hip), thigh, shin, spine (2: y, z of mid-shoulder from
    mid-hip), shoulder_x (half shoulder width; neck = mid-shoulder), upperarm, forearm,
    nose (2: y, z from neck), eye (3: left eye from neck; right = x mirrored), ear (3)
"""

from __future__ import annotations

import numpy as np
import torch

NODE_NAMES: tuple[str, ...] = (
    "pelvis", "l_hip", "l_knee", "l_ankle", "r_hip", "r_knee", "r_ankle", "spine", "neck",
    "l_shoulder", "l_elbow", "l_wrist", "r_shoulder", "r_elbow", "r_wrist", "head",
    "nose", "l_eye", "r_eye", "l_ear", "r_ear",
)  # fmt: skip
PARENTS = np.array([-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 9, 10, 8, 12, 13, 8, 15, 15, 15, 15, 15])
#: COCO-17 index -> node index
COCO_TO_NODE = np.array([16, 17, 18, 19, 20, 9, 12, 10, 13, 11, 14, 1, 4, 2, 5, 3, 6])
#: Nodes with a rotation parameter (besides the root), pose order.
POSE_JOINTS = np.array([1, 2, 4, 5, 7, 8, 9, 10, 12, 13, 15])
POSE_JOINT_NAMES = tuple(NODE_NAMES[j] for j in POSE_JOINTS)
NUM_POSE = len(POSE_JOINTS)
SHAPE_NAMES: tuple[str, ...] = (
    "hip_x", "thigh", "shin", "spine_y", "spine_z", "shoulder_x", "upperarm", "forearm",
    "nose_y", "nose_z", "eye_x", "eye_y", "eye_z", "ear_x", "ear_y", "ear_z",
)  # fmt: skip
NUM_SHAPE = len(SHAPE_NAMES)
#: Rough adult shape (used only where no better one is given).
DEFAULT_SHAPE = np.array([0.09, 0.42, 0.41, 0.50, -0.02, 0.17, 0.28, 0.26, 0.20, 0.10, 0.03, 0.22, 0.08, 0.075, 0.19, -0.0])


def rest_offsets(shape, xp=np):
    """Rest offsets (..., 21, 3) of every node from its parent, from shape vectors (..., 16).

    ``xp`` is numpy or torch (the function is differentiable in torch).
    """
    s = shape
    z = s[..., 0] * 0.0

    def v(a, b, c):
        return xp.stack([a, b, c], -1)

    nodes = [
        v(z, z, z),  # pelvis
        v(s[..., 0], z, z), v(z, -s[..., 1], z), v(z, -s[..., 2], z),  # left leg
        v(-s[..., 0], z, z), v(z, -s[..., 1], z), v(z, -s[..., 2], z),  # right leg
        v(z, z, z), v(z, s[..., 3], s[..., 4]),  # spine, neck
        v(s[..., 5], z, z), v(s[..., 6], z, z), v(s[..., 7], z, z),  # left arm
        v(-s[..., 5], z, z), v(-s[..., 6], z, z), v(-s[..., 7], z, z),  # right arm
        v(z, z, z), v(z, s[..., 8], s[..., 9]),  # head, nose
        v(s[..., 10], s[..., 11], s[..., 12]), v(-s[..., 10], s[..., 11], s[..., 12]),  # eyes
        v(s[..., 13], s[..., 14], s[..., 15]), v(-s[..., 13], s[..., 14], s[..., 15]),  # ears
    ]
    return xp.stack(nodes, -2)


def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """Rodrigues: (..., 3) axis-angle -> (..., 3, 3), smooth at zero."""
    theta2 = (aa * aa).sum(-1, keepdim=True)
    theta = torch.sqrt(theta2 + 1e-12)
    k = aa / theta
    # Taylor-safe coefficients
    small = theta2 < 1e-8
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / torch.clamp(theta2, min=1e-12))
    x, y, zz = aa[..., 0], aa[..., 1], aa[..., 2]
    zero = torch.zeros_like(x)
    Kx = torch.stack([zero, -zz, y, zz, zero, -x, -y, x, zero], -1).reshape(aa.shape[:-1] + (3, 3))
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand(aa.shape[:-1] + (3, 3))
    del k
    return eye + a[..., None] * Kx + b[..., None] * (Kx @ Kx)


def forward_kinematics_torch(R_root: torch.Tensor, R_local: torch.Tensor, transl: torch.Tensor, shape: torch.Tensor) -> torch.Tensor:
    """Node positions (B, 21, 3) in the frame of ``R_root``/``transl``.

    Shapes: R_root (B, 3, 3) body -> world, R_local (B, 11, 3, 3) in :data:`POSE_JOINTS` order,
    transl (B, 3) pelvis position, shape (B, 16) or (16,).
    """
    B = R_root.shape[0]
    off = rest_offsets(shape, torch)
    if off.dim() == 2:
        off = off.expand(B, -1, -1)
    G: list = [None] * 21
    P: list = [None] * 21
    G[0] = R_root
    P[0] = transl
    slot = {int(j): i for i, j in enumerate(POSE_JOINTS)}
    for j in range(1, 21):
        p = int(PARENTS[j])
        P[j] = P[p] + (G[p] @ off[:, j, :, None])[..., 0]
        G[j] = G[p] @ R_local[:, slot[j]] if j in slot else G[p]
    return torch.stack(P, 1)


def forward_kinematics_np(R_root: np.ndarray, R_local: np.ndarray, transl: np.ndarray, shape: np.ndarray) -> np.ndarray:
    """numpy twin of :func:`forward_kinematics_torch`; shapes (T, 3, 3), (T, 11, 3, 3), (T, 3), (16,)."""
    out = forward_kinematics_torch(
        torch.as_tensor(R_root, dtype=torch.float64), torch.as_tensor(R_local, dtype=torch.float64),
        torch.as_tensor(transl, dtype=torch.float64), torch.as_tensor(shape, dtype=torch.float64),
    )  # fmt: skip
    return out.numpy()


def nodes_from_coco(joints: np.ndarray) -> np.ndarray:
    """Node positions (T, 21, 3) from COCO-17 (T, 17, 3): pelvis = mid-hip, neck = mid-shoulder, spine/head at them."""
    T = joints.shape[0]
    n = np.zeros((T, 21, 3))
    n[:, COCO_TO_NODE] = joints
    n[:, 0] = 0.5 * (joints[:, 11] + joints[:, 12])
    n[:, 7] = n[:, 0]
    n[:, 8] = 0.5 * (joints[:, 5] + joints[:, 6])
    n[:, 15] = n[:, 8]
    return n


def _unit(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotations (T, 3, 3) taking directions a (T,3) onto b (T,3)."""
    a, b = _unit(a), _unit(b)
    v = np.cross(a, b)
    c = np.sum(a * b, -1)
    s = np.linalg.norm(v, axis=-1)
    K = np.zeros(a.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    f = np.where(s > 1e-9, (1 - c) / np.maximum(s**2, 1e-18), 0.5)[..., None, None]
    R = np.eye(3) + K + f * (K @ K)
    # antiparallel: rotate pi about any axis orthogonal to a
    anti = (s < 1e-9) & (c < 0)
    if np.any(anti):
        ax = _unit(np.cross(a[anti], np.where(np.abs(a[anti, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])))
        R[anti] = 2 * ax[:, :, None] * ax[:, None, :] - np.eye(3)
    return R


def _kabsch(A: np.ndarray, B: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Rotations (T, 3, 3) best mapping rest vectors A (K, 3) onto B (T, K, 3) with weights w (K,)."""
    H = np.einsum("k,ki,tkj->tij", w, A, B)  # sum w a b^T
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    D = np.zeros_like(H)
    D[:, 0, 0] = D[:, 1, 1] = 1
    D[:, 2, 2] = d
    return np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)


def _axis_then_roll(axis_rest: np.ndarray, axis_t: np.ndarray, others_rest: np.ndarray, others_t: np.ndarray) -> np.ndarray:
    """Rotations (T, 3, 3) taking ``axis_rest`` (3,) exactly onto the direction ``axis_t`` (T, 3), with
    the roll about it that best aligns ``others_rest`` (K, 3) with ``others_t`` (T, K, 3)."""
    R1 = _min_rotation(np.broadcast_to(axis_rest, axis_t.shape), axis_t)
    n = _unit(axis_t)
    a = np.einsum("tij,kj->tki", R1, others_rest)
    a = a - n[:, None] * np.sum(a * n[:, None], -1, keepdims=True)
    b = others_t - n[:, None] * np.sum(others_t * n[:, None], -1, keepdims=True)
    phi = np.arctan2(np.sum(np.cross(a, b) * n[:, None], (-1, -2)), np.sum(a * b, (-1, -2)))
    K = np.zeros(n.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -n[..., 2], n[..., 1], -n[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = n[..., 2], -n[..., 1], n[..., 0]
    s, c = np.sin(phi)[:, None, None], np.cos(phi)[:, None, None]
    return (np.eye(3) + s * K + (1 - c) * (K @ K)) @ R1


def inverse_kinematics(joints: np.ndarray, shape: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotations that put the skeleton on COCO-17 joints (T, 17, 3) given its shape (16,).

    Returns (R_root (T, 3, 3), R_local (T, 11, 3, 3), transl (T, 3)). Exact when the joints are a
    rigid instance of the skeleton (same bone lengths and face/hip/shoulder geometry as ``shape``);
    otherwise the limb directions are exact and lengths those of ``shape``. Single-child joints get the
    smallest rotation (no twist about the bone).
    """
    J = nodes_from_coco(np.asarray(joints, dtype=float))
    T = J.shape[0]
    off = rest_offsets(np.asarray(shape, dtype=float))
    G = np.zeros((T, 21, 3, 3))
    L = np.broadcast_to(np.eye(3), (T, 21, 3, 3)).copy()
    # root: the hip axis exactly, the neck direction for the roll about it
    G[:, 0] = _axis_then_roll(off[1] - off[4], J[:, 1] - J[:, 4], off[8][None], (J[:, 8] - J[:, 0])[:, None])
    for j in range(1, 21):
        p = PARENTS[j]
        Gp = G[:, p] if p != 7 and p != 15 else G[:, p]
        children = [c for c in range(21) if PARENTS[c] == j]
        if j not in POSE_JOINTS:
            G[:, j] = Gp
            continue
        to_local = np.swapaxes(Gp, -1, -2)
        if j == 7:  # spine: turns the rest spine offset onto the actual neck direction
            b = np.einsum("tij,tj->ti", to_local, J[:, 8] - J[:, 7])
            L[:, j] = _min_rotation(np.broadcast_to(off[8], b.shape), b)
        elif j == 8:  # neck: the shoulder axis exactly, the face for the roll about it
            A = np.stack([off[k] for k in (16, 17, 18, 19, 20)])
            Bv = np.stack([J[:, k] - J[:, 8] for k in (16, 17, 18, 19, 20)], 1)
            L[:, j] = _axis_then_roll(off[9] - off[12], np.einsum("tij,tj->ti", to_local, J[:, 9] - J[:, 12]),
                                      A, np.einsum("tij,tkj->tki", to_local, Bv))  # fmt: skip
        elif j == 15:  # head: face points
            ks = (16, 17, 18, 19, 20)
            A = np.stack([off[k] for k in ks])
            Bv = np.stack([J[:, k] - J[:, 15] for k in ks], 1)
            L[:, j] = _kabsch(A, np.einsum("tij,tkj->tki", to_local, Bv), np.ones(5))
        else:
            (c,) = children
            b = np.einsum("tij,tj->ti", to_local, J[:, c] - J[:, j])
            L[:, j] = _min_rotation(np.broadcast_to(off[c], b.shape), b)
        G[:, j] = Gp @ L[:, j]
    return G[:, 0], L[:, POSE_JOINTS], J[:, 0]


def estimate_shape(joints: np.ndarray) -> np.ndarray:
    """A shape vector (16,) from COCO-17 joint sequences (T, 17, 3) (medians over frames).

    Limb lengths, hip/shoulder half-widths and spine length are measured directly; the hip/shoulder
    offsets' vertical/forward parts and the face geometry are measured in a trunk frame per frame.
    """
    J = nodes_from_coco(np.asarray(joints, dtype=float))
    med = lambda x: float(np.median(x))  # noqa: E731
    ln = lambda a, b: np.linalg.norm(J[:, a] - J[:, b], axis=-1)  # noqa: E731
    s = np.array(DEFAULT_SHAPE, dtype=float)
    s[0] = med(ln(1, 4)) / 2
    s[1] = med(np.r_[ln(1, 2), ln(4, 5)])
    s[2] = med(np.r_[ln(2, 3), ln(5, 6)])
    s[3] = med(ln(8, 0))
    s[4] = 0.0
    s[5] = med(ln(9, 12)) / 2
    s[6] = med(np.r_[ln(9, 10), ln(12, 13)])
    s[7] = med(np.r_[ln(10, 11), ln(13, 14)])
    # face in a neck frame: x = shoulder axis (left), y = up along the spine, z = forward
    x = _unit(J[:, 9] - J[:, 12])
    up = J[:, 8] - J[:, 0]
    y = _unit(up - x * np.sum(up * x, -1, keepdims=True))
    z = np.cross(x, y)
    Rm = np.stack([x, y, z], -1)  # local -> world
    loc = lambda k: np.einsum("tji,tj->ti", Rm, J[:, k] - J[:, 8])  # noqa: E731
    nose, le, re, lea, rea = (loc(k) for k in (16, 17, 18, 19, 20))
    s[8], s[9] = np.median(nose[:, 1]), np.median(nose[:, 2])
    s[10:13] = np.median(np.concatenate([le, re * [-1, 1, 1]]), 0)
    s[13:16] = np.median(np.concatenate([lea, rea * [-1, 1, 1]]), 0)
    return s
