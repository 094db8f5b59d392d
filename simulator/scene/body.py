"""The rendered body: 17 ellipsoids (head, hair, neck, chest, pelvis, upper/lower arms, hands, thighs,
shins, feet) built from the 17 COCO joints alone, so that anything carrying COCO-17 joints (a
``SimTruth`` message included) can be rendered.

An ellipsoid is a centre ``c`` (3,) and a matrix ``M`` (3, 3) with ``|M (x - c)| <= 1`` inside;
``M = diag(1 / radii) @ axes.T`` (axes as columns). Its "dual shape" ``B = M^-1 M^-T = axes diag(r^2) axes.T``
gives exact image outlines (see :mod:`simulator.scene.camera`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: Part names, in the order of :func:`body_ellipsoids`'s output, and their material.
PARTS: tuple[tuple[str, str], ...] = (
    ("head", "skin"), ("hair", "hair"), ("neck", "skin"), ("chest", "shirt"), ("pelvis", "trousers"),
    ("l_upperarm", "shirt"), ("r_upperarm", "shirt"), ("l_forearm", "skin"), ("r_forearm", "skin"),
    ("l_hand", "skin"), ("r_hand", "skin"),
    ("l_thigh", "trousers"), ("r_thigh", "trousers"), ("l_shin", "trousers"), ("r_shin", "trousers"),
    ("l_foot", "shoes"), ("r_foot", "shoes"),
)  # fmt: skip
MATERIALS = ("skin", "shirt", "trousers", "shoes", "hair")
PART_MATERIAL = np.array([MATERIALS.index(m) for _, m in PARTS])

# Bones (COCO indices from, to, radius m) for the limb ellipsoids.
_BONES = ((5, 7, 0.046), (6, 8, 0.046), (7, 9, 0.038), (8, 10, 0.038), (11, 13, 0.078), (12, 14, 0.078), (13, 15, 0.057), (14, 16, 0.057))


@dataclasses.dataclass
class Ellipsoids:
    """E ellipsoids: centres (E, 3), M (E, 3, 3) (``|M (x - c)| <= 1`` inside), B (E, 3, 3) = M^-1 M^-T,
    material (E,) index into :data:`MATERIALS`."""

    centers: np.ndarray
    M: np.ndarray
    B: np.ndarray
    material: np.ndarray

    def transformed(self, R: np.ndarray, t: np.ndarray) -> "Ellipsoids":
        """The same ellipsoids in another frame: x' = R x + t."""
        c = self.centers @ R.T + t
        M = self.M @ R.T
        B = R @ self.B @ R.T
        return Ellipsoids(c, M, B, self.material)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def _perp_basis(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (N, 3) completing unit vectors u (N, 3) to orthonormal frames."""
    a = np.where(np.abs(u[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    v = _unit(np.cross(u, a))
    w = np.cross(u, v)
    return v, w


def body_ellipsoids(joints: np.ndarray) -> Ellipsoids:
    """The body's 17 ellipsoids (order of :data:`PARTS`) from COCO-17 joints (17, 3) in NED metres."""
    j = np.asarray(joints, dtype=float)
    up_w = np.array([0.0, 0.0, -1.0])
    sh_mid = 0.5 * (j[5] + j[6])
    hip_mid = 0.5 * (j[11] + j[12])
    ear_mid = 0.5 * (j[3] + j[4])
    # torso frame
    up_t = _unit(sh_mid - hip_mid)
    left_t = j[5] - j[6] + (j[11] - j[12])
    left_t = _unit(left_t - up_t * np.dot(left_t, up_t))
    fwd_t = np.cross(left_t, up_t)
    L_t = float(np.linalg.norm(sh_mid - hip_mid))
    sh_w = float(np.linalg.norm(j[5] - j[6]))
    hip_w = float(np.linalg.norm(j[11] - j[12]))
    # head frame
    left_h = _unit(j[3] - j[4])
    fwd_h = j[0] - ear_mid
    fwd_h = _unit(fwd_h - left_h * np.dot(fwd_h, left_h))
    up_h = np.cross(fwd_h, left_h)
    # horizontal forward of the hips (for the feet)
    fwd_f = _unit(np.cross(j[11] - j[12], up_w))

    centers, axes, radii = [], [], []

    def add(c, ax_cols, r):
        centers.append(c)
        axes.append(np.stack(ax_cols, axis=1))
        radii.append(r)

    head_c = ear_mid + 0.03 * up_h + 0.025 * fwd_h
    add(head_c, (fwd_h, left_h, up_h), (0.10, 0.08, 0.12))
    # hair: covers the back, top and sides of the head, leaves the face (front reaches 0.06 < 0.10)
    add(head_c - 0.03 * fwd_h + 0.02 * up_h, (fwd_h, left_h, up_h), (0.09, 0.086, 0.112))
    head_base = ear_mid - 0.06 * up_h
    neck_axis = head_base - sh_mid
    nL = max(float(np.linalg.norm(neck_axis)), 1e-3)
    nu = neck_axis / nL
    nv, nw = _perp_basis(nu[None])
    add(sh_mid + 0.5 * neck_axis, (nu, nv[0], nw[0]), (0.5 * nL + 0.03, 0.055, 0.055))
    # chest: from the waist to above the shoulder joints (the trapezius); pelvis: hips and belly
    add(hip_mid + 0.70 * L_t * up_t - 0.01 * fwd_t, (fwd_t, left_t, up_t), (0.11, 0.5 * sh_w * 0.92, 0.41 * L_t))
    add(hip_mid + 0.17 * L_t * up_t, (fwd_t, left_t, up_t), (0.10, 0.5 * hip_w + 0.055, 0.33 * L_t))
    # limbs
    a = np.array([b[0] for b in _BONES])
    b = np.array([b[1] for b in _BONES])
    r = np.array([b_[2] for b_ in _BONES])
    d = j[b] - j[a]
    Lb = np.maximum(np.linalg.norm(d, axis=-1), 1e-3)
    u = d / Lb[:, None]
    v, w = _perp_basis(u)
    limb_c = 0.5 * (j[a] + j[b])
    limb_ax = np.stack([u, v, w], axis=2)
    limb_r = np.stack([0.5 * Lb + 0.5 * r, r, r], axis=1)
    # hands: continue the forearm past the wrist
    hu = u[2:4]
    hand_c = j[[9, 10]] + 0.07 * hu
    hv, hw = _perp_basis(hu)
    # feet: ankle -> forward along the hips' horizontal forward, a little lower
    foot_c = j[[15, 16]] + 0.07 * fwd_f + np.array([0.0, 0.0, 0.045])
    foot_left = np.cross(up_w, fwd_f)
    order_c = [limb_c[0], limb_c[1], limb_c[2], limb_c[3], hand_c[0], hand_c[1],
               limb_c[4], limb_c[5], limb_c[6], limb_c[7], foot_c[0], foot_c[1]]  # fmt: skip
    order_ax = [limb_ax[0], limb_ax[1], limb_ax[2], limb_ax[3],
                np.stack([hu[0], hv[0], hw[0]], 1), np.stack([hu[1], hv[1], hw[1]], 1),
                limb_ax[4], limb_ax[5], limb_ax[6], limb_ax[7],
                np.stack([fwd_f, foot_left, -up_w], 1), np.stack([fwd_f, foot_left, -up_w], 1)]  # fmt: skip
    order_r = [limb_r[0], limb_r[1], limb_r[2], limb_r[3], (0.075, 0.045, 0.025), (0.075, 0.045, 0.025),
               limb_r[4], limb_r[5], limb_r[6], limb_r[7], (0.13, 0.05, 0.045), (0.13, 0.05, 0.045)]  # fmt: skip
    for c_, ax_, r_ in zip(order_c, order_ax, order_r):
        centers.append(c_)
        axes.append(ax_)
        radii.append(r_)
    C = np.array(centers)
    A = np.array(axes)  # (E, 3, 3) columns = axes
    Rr = np.array(radii, dtype=float)
    M = (1.0 / Rr)[:, :, None] * np.swapaxes(A, 1, 2)
    B = A @ (Rr[:, :, None] ** 2 * np.swapaxes(A, 1, 2))
    return Ellipsoids(C, M, B, PART_MATERIAL.copy())
