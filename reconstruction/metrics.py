"""Evaluation metrics for 3D joint reconstructions (shared by every method, the harnesses and the flight summary).

All functions take joints as arrays (T, J, 3) (or (J, 3)) in metres and return millimetres. The names are the
field's:

* ``mpjpe_mm`` -- MPJPE, Human3.6M protocol 1: mean Euclidean joint distance after subtracting each skeleton's
  root (the mid-hip, :data:`ROOT_JOINTS`) per frame. The pose and its world orientation, not its place.
* ``pa_mpjpe_mm`` -- PA-MPJPE, protocol 2: the same after the best similarity transform (rotation, translation,
  scale) per frame (Umeyama 1991): the pose alone, the metric of DroCap and most monocular work.
* ``w_mpjpe_mm`` -- world MPJPE: no alignment at all (both in the same world frame): what a capture delivers.
* ``root_err_mm`` -- mean distance between the estimated and the true root (mid-hip).

:func:`accuracy_metrics` gives all four, plus per joint group (:data:`BODY_GROUPS`: torso / arms / legs / head),
as one dict with those key names (``suffix`` e.g. ``"_window"`` appended), used by ``summary.json`` →
``reconstruction.accuracy_vs_truth`` and the evaluation harnesses' ``metrics.json``.
"""

from __future__ import annotations

import numpy as np

from skycap.errors import SkycapError
from skycap.skeleton import SCORED_JOINTS

__all__ = ["ROOT_JOINTS", "BODY_GROUPS", "METRIC_KEYS", "MetricsError", "similarity_procrustes", "procrustes_align",
           "root_positions", "mpjpe_mm", "pa_mpjpe_mm", "w_mpjpe_mm", "root_err_mm", "per_joint_errors_mm",
           "accuracy_metrics"]

#: The root of the COCO-17 skeleton: the mid-point of the hips (COCO-17 has no pelvis joint).
ROOT_JOINTS: tuple[int, ...] = (11, 12)

#: Scored-joint groups of the summary (COCO-17 indices; each a subset of SCORED_JOINTS).
BODY_GROUPS: dict[str, tuple[int, ...]] = {
    "torso": (5, 6, 11, 12),  # shoulders, hips
    "arms": (7, 8, 9, 10),  # elbows, wrists
    "legs": (13, 14, 15, 16),  # knees, ankles
    "head": (0,),  # nose
}

#: The scalar metrics of :func:`accuracy_metrics`, in the order tables print them.
METRIC_KEYS: tuple[str, ...] = ("mpjpe_mm", "pa_mpjpe_mm", "w_mpjpe_mm", "root_err_mm")


class MetricsError(SkycapError):
    """Joint arrays that cannot be scored together."""


def similarity_procrustes(X: np.ndarray, Y: np.ndarray, weights: np.ndarray | None = None):
    """Best (s, R, t) with s * R @ X_j + t ~= Y_j in least squares (Umeyama).

    Shapes: X, Y (J, 3) -> s (), R (3, 3) with det +1, t (3,). ``weights`` (J,) optional (>= 0).
    """
    X = np.asarray(X, dtype=float)
    Y = np.asarray(Y, dtype=float)
    w = np.ones(len(X)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    mx = w @ X
    my = w @ Y
    Xc = X - mx
    Yc = Y - my
    cov = (Yc * w[:, None]).T @ Xc
    U, S, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.diag([1.0, 1.0, d])
    R = U @ D @ Vt
    var_x = np.sum(w * np.sum(Xc**2, axis=1))
    s = float(np.trace(np.diag(S) @ D) / var_x) if var_x > 0 else 1.0
    t = my - s * R @ mx
    return s, R, t


def procrustes_align(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``pred`` aligned to ``gt`` by the per-frame similarity transform. Shapes (T, J, 3) or (J, 3).
    A frame with a non-finite joint stays NaN."""
    pred = np.asarray(pred, dtype=float)
    gt = np.asarray(gt, dtype=float)
    if pred.ndim == 2:
        if not (np.isfinite(pred).all() and np.isfinite(gt).all()):
            return np.full_like(pred, np.nan)
        s, R, t = similarity_procrustes(pred, gt)
        return s * pred @ R.T + t
    return np.stack([procrustes_align(p, g) for p, g in zip(pred, gt)])


def _pair(pred, gt) -> tuple[np.ndarray, np.ndarray]:
    pred = np.asarray(pred, dtype=float)
    gt = np.asarray(gt, dtype=float)
    if pred.shape != gt.shape or pred.shape[-1] != 3:
        raise MetricsError(f"prediction {pred.shape} and truth {gt.shape} must be the same shape (..., J, 3)")
    return pred, gt


def root_positions(joints: np.ndarray, root_joints=ROOT_JOINTS) -> np.ndarray:
    """The root (..., 3): the mean of ``root_joints`` (default the hips: COCO-17 mid-hip)."""
    joints = np.asarray(joints, dtype=float)
    idx = list(root_joints)
    if joints.shape[-2] <= max(idx):
        raise MetricsError(f"joints of shape {joints.shape} have no root joints {idx}: pass COCO-17 joints (J=17) or "
                           "name the root with root_joints")
    return joints[..., idx, :].mean(axis=-2)


def per_joint_errors_mm(pred: np.ndarray, gt: np.ndarray, aligned: bool = False) -> np.ndarray:
    """Per-frame, per-joint world errors (T, J) in mm (no alignment); ``aligned`` applies per-frame Procrustes first."""
    pred, gt = _pair(pred, gt)
    if aligned:
        pred = procrustes_align(pred, gt)
    return 1000.0 * np.linalg.norm(pred - gt, axis=-1)


def _select(e: np.ndarray, joints) -> np.ndarray:
    return e if joints is None else e[..., list(joints)]


def w_mpjpe_mm(pred: np.ndarray, gt: np.ndarray, joints=None) -> float:
    """World MPJPE (mm): mean per-joint distance without any alignment; ``joints`` selects joint indices."""
    return float(np.nanmean(_select(per_joint_errors_mm(pred, gt), joints)))


def mpjpe_mm(pred: np.ndarray, gt: np.ndarray, joints=None, root_joints=ROOT_JOINTS) -> float:
    """MPJPE (mm), Human3.6M protocol 1: each skeleton's root (``root_joints``, default the mid-hip, taken from
    all joints) subtracted per frame, then the mean per-joint distance over ``joints`` (default all)."""
    pred, gt = _pair(pred, gt)
    rp, rg = root_positions(pred, root_joints), root_positions(gt, root_joints)
    return float(np.nanmean(_select(per_joint_errors_mm(pred - rp[..., None, :], gt - rg[..., None, :]), joints)))


def pa_mpjpe_mm(pred: np.ndarray, gt: np.ndarray, joints=None) -> float:
    """PA-MPJPE (mm), protocol 2: mean per-joint error after the per-frame similarity alignment over the selected
    joints (frames with a non-finite joint are left out)."""
    pred, gt = _pair(pred, gt)
    if joints is not None:
        pred = pred[..., list(joints), :]
        gt = gt[..., list(joints), :]
    return float(np.nanmean(per_joint_errors_mm(pred, gt, aligned=True)))


def root_err_mm(pred: np.ndarray, gt: np.ndarray, root_joints=ROOT_JOINTS) -> float:
    """Mean distance (mm) between the estimated and the true root (default the mid-hip)."""
    pred, gt = _pair(pred, gt)
    return float(np.nanmean(1000.0 * np.linalg.norm(root_positions(pred, root_joints) - root_positions(gt, root_joints),
                                                     axis=-1)))


def accuracy_metrics(pred: np.ndarray, gt: np.ndarray, joints=SCORED_JOINTS, groups: dict | None = None,
                     suffix: str = "", ndigits: int | None = 1) -> dict:
    """Every accuracy figure of COCO-17 joints ``pred`` against ``gt`` (T, 17, 3), metres, same frames.

    Returns ``frames_scored``, ``mpjpe_mm`` (root-aligned, protocol 1), ``pa_mpjpe_mm`` (protocol 2),
    ``w_mpjpe_mm`` (world, no alignment), ``root_err_mm`` over ``joints`` (default :data:`SCORED_JOINTS`), and
    ``per_group_mm`` {group: {mpjpe_mm, pa_mpjpe_mm, w_mpjpe_mm}} over ``groups`` (default :data:`BODY_GROUPS`;
    the PA figure of a group is its joints' errors after the alignment over all ``joints``), each key with
    ``suffix`` appended (e.g. ``"_window"``); values rounded to ``ndigits`` (None: not rounded)."""
    pred, gt = _pair(pred, gt)
    if pred.ndim == 2:
        pred, gt = pred[None], gt[None]
    if pred.shape[1] != 17:
        raise MetricsError(f"accuracy_metrics scores COCO-17 joints (T, 17, 3); got {pred.shape}")
    sj = list(joints)
    groups = BODY_GROUPS if groups is None else groups
    rp, rg = root_positions(pred), root_positions(gt)
    e_w = per_joint_errors_mm(pred, gt)  # (T, 17)
    e_r = per_joint_errors_mm(pred - rp[:, None], gt - rg[:, None])
    e_pa = np.full_like(e_w, np.nan)
    e_pa[:, sj] = per_joint_errors_mm(pred[:, sj], gt[:, sj], aligned=True)

    def r(x: float) -> float:
        return float(x) if ndigits is None else round(float(x), ndigits)

    def mean(e: np.ndarray, idx) -> float:
        v = e[:, list(idx)]
        return float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")

    return {
        f"frames_scored{suffix}": int(len(pred)),
        f"mpjpe_mm{suffix}": r(mean(e_r, sj)),
        f"pa_mpjpe_mm{suffix}": r(mean(e_pa, sj)),
        f"w_mpjpe_mm{suffix}": r(mean(e_w, sj)),
        f"root_err_mm{suffix}": r(float(np.nanmean(1000.0 * np.linalg.norm(rp - rg, axis=-1)))),
        f"per_group_mm{suffix}": {g: {"mpjpe_mm": r(mean(e_r, idx)), "pa_mpjpe_mm": r(mean(e_pa, idx)),
                                      "w_mpjpe_mm": r(mean(e_w, idx))} for g, idx in groups.items()},
    }
