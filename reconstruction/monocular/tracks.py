"""2D keypoint track cleaning before the single-frame initialisation.

Gross detector errors (a joint put on the background, a left/right swap) are jumps in a joint's image
track, whereas the true track moves smoothly at video rate. :func:`temporal_outlier_mask` compares each
keypoint with the median of its neighbours in time (excluding itself) and flags those farther away than a
fraction of the person's image size; the initialisation then gives them zero weight.
"""

from __future__ import annotations

import numpy as np

__all__ = ["temporal_outlier_mask"]


def temporal_outlier_mask(W_px: np.ndarray, confidence: np.ndarray, half_window: int = 3, threshold_rel: float = 0.2) -> np.ndarray:
    """Boolean (T, J): True where a detected keypoint is far from the temporal median of its neighbours.

    Args:
        W_px: (T, 2, J) keypoints in pixels (NaN where missing).
        confidence: (T, J), 0 = missing (ignored, never flagged).
        half_window: neighbours on each side (the keypoint itself is excluded from its median).
        threshold_rel: threshold as a fraction of the frame's person size (RMS radius of the keypoints
            about their median centre, robust to a few outliers).
    """
    W = np.where((confidence > 0)[:, None, :] & np.isfinite(W_px), W_px, np.nan)
    T = W.shape[0]
    idx = np.arange(T)[:, None] + np.concatenate([np.arange(-half_window, 0), np.arange(1, half_window + 1)])[None]
    valid = (idx >= 0) & (idx < T)
    nb = W[np.clip(idx, 0, T - 1)]  # (T, 2h, 2, J)
    nb = np.where(valid[:, :, None, None], nb, np.nan)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(nb, axis=1)  # (T, 2, J)
            centre = np.nanmedian(W, axis=2, keepdims=True)
            size = np.sqrt(np.nanmedian(np.sum((W - centre) ** 2, axis=1), axis=1))  # (T,)
    dist = np.linalg.norm(W - med, axis=1)  # (T, J)
    flag = dist > threshold_rel * size[:, None]
    return np.where(np.isfinite(dist), flag, False)
