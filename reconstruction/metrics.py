"""Evaluation metrics for 3D joint reconstructions (shared by every method).

All functions take joints as arrays (T, J, 3) (or (J, 3)) in metres and return millimetres.

* MPJPE: mean Euclidean distance per joint, after no alignment (both in the same world frame).
* PA-MPJPE: the same after the best similarity transform (rotation, translation and scale) per
  frame (Umeyama 1991), the metric of DroCap and most monocular work.
"""

from __future__ import annotations

import numpy as np

__all__ = ["similarity_procrustes", "procrustes_align", "mpjpe_mm", "pa_mpjpe_mm", "per_joint_errors_mm"]


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
    """``pred`` aligned to ``gt`` by the per-frame similarity transform. Shapes (T, J, 3) or (J, 3)."""
    pred = np.asarray(pred, dtype=float)
    gt = np.asarray(gt, dtype=float)
    if pred.ndim == 2:
        s, R, t = similarity_procrustes(pred, gt)
        return s * pred @ R.T + t
    return np.stack([procrustes_align(p, g) for p, g in zip(pred, gt)])


def per_joint_errors_mm(pred: np.ndarray, gt: np.ndarray, aligned: bool = False) -> np.ndarray:
    """Per-frame, per-joint errors (T, J) in mm; ``aligned`` applies per-frame Procrustes first."""
    pred = np.asarray(pred, dtype=float)
    gt = np.asarray(gt, dtype=float)
    if aligned:
        pred = procrustes_align(pred, gt)
    return 1000.0 * np.linalg.norm(pred - gt, axis=-1)


def mpjpe_mm(pred: np.ndarray, gt: np.ndarray, joints=None) -> float:
    """Mean per-joint position error (mm) without alignment; ``joints`` selects joint indices."""
    e = per_joint_errors_mm(pred, gt)
    if joints is not None:
        e = e[..., list(joints)]
    return float(np.nanmean(e))


def pa_mpjpe_mm(pred: np.ndarray, gt: np.ndarray, joints=None) -> float:
    """Mean per-joint error (mm) after per-frame similarity alignment over the selected joints."""
    pred = np.asarray(pred, dtype=float)
    gt = np.asarray(gt, dtype=float)
    if joints is not None:
        pred = pred[..., list(joints), :]
        gt = gt[..., list(joints), :]
    return float(np.mean(per_joint_errors_mm(pred, gt, aligned=True)))
