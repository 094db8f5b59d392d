"""2D keypoint track cleaning before the single-frame initialisation.

Gross detector errors (a joint put on the background, a left/right swap) are jumps in a joint's image
track, whereas the true track moves smoothly at video rate. :func:`temporal_outlier_mask` compares each
keypoint with the median of its neighbours in time (excluding itself) and flags those farther away than a
fraction of the person's image size, or, for a small (far) person, farther than a few times the typical
deviation of the tracks (:func:`track_noise_px`, the detector noise plus the motion between frames): a
threshold relative to the person's size alone flags most keypoints of a person 50 px tall seen with a few
pixels of noise (a real single-drone flight: 66 % of the keypoints were flagged). The initialisation then
gives the flagged keypoints zero weight.
"""

from __future__ import annotations

import warnings

import numpy as np

__all__ = ["temporal_outlier_mask", "track_noise_px"]


def _neighbour_deviation(W_px: np.ndarray, confidence: np.ndarray, half_window: int):
    """Distance (T, J) of each keypoint from the median of its temporal neighbours (NaN where undefined),
    and the per-frame person size (T,) (RMS radius about the median centre, robust to a few outliers)."""
    W = np.where((confidence > 0)[:, None, :] & np.isfinite(W_px), W_px, np.nan)
    T = W.shape[0]
    idx = np.arange(T)[:, None] + np.concatenate([np.arange(-half_window, 0), np.arange(1, half_window + 1)])[None]
    valid = (idx >= 0) & (idx < T)
    nb = W[np.clip(idx, 0, T - 1)]  # (T, 2h, 2, J)
    nb = np.where(valid[:, :, None, None], nb, np.nan)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(nb, axis=1)  # (T, 2, J)
        centre = np.nanmedian(W, axis=2, keepdims=True)
        size = np.sqrt(np.nanmedian(np.sum((W - centre) ** 2, axis=1), axis=1))  # (T,)
    return np.linalg.norm(W - med, axis=1), size


def track_noise_px(W_px: np.ndarray, confidence: np.ndarray, half_window: int = 3) -> float:
    """Robust typical deviation (pixels) of a keypoint from the temporal median of its neighbours.

    The median over all keypoints of that distance (gross outliers are a minority and do not move it); it
    contains the detector noise and the motion between frames, so it is a scale for "normal" track jitter.
    Returns 0.0 when no keypoint has neighbours. Shapes: W_px (T, 2, J), confidence (T, J).
    """
    dist, _ = _neighbour_deviation(np.asarray(W_px, dtype=float), np.asarray(confidence, dtype=float), half_window)
    d = dist[np.isfinite(dist)]
    return float(np.median(d)) if d.size else 0.0


def temporal_outlier_mask(
    W_px: np.ndarray,
    confidence: np.ndarray,
    half_window: int = 3,
    threshold_rel: float = 0.2,
    noise_mult: float = 2.0,
) -> np.ndarray:
    """Boolean (T, J): True where a detected keypoint is far from the temporal median of its neighbours.

    Args:
        W_px: (T, 2, J) keypoints in pixels (NaN where missing).
        confidence: (T, J), 0 = missing (ignored, never flagged).
        half_window: neighbours on each side (the keypoint itself is excluded from its median).
        threshold_rel: threshold as a fraction of the frame's person size (RMS radius of the keypoints
            about their median centre, robust to a few outliers).
        noise_mult: the threshold is at least ``noise_mult`` times :func:`track_noise_px` (0 = no floor).
    """
    dist, size = _neighbour_deviation(np.asarray(W_px, dtype=float), np.asarray(confidence, dtype=float), half_window)
    d = dist[np.isfinite(dist)]
    floor = noise_mult * float(np.median(d)) if (d.size and noise_mult > 0) else 0.0
    with np.errstate(invalid="ignore"):
        flag = dist > np.maximum(threshold_rel * size[:, None], floor)
    return np.where(np.isfinite(dist), flag, False)
