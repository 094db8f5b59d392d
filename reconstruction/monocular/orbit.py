"""The orthographic orbiting camera of DroCap's synthetic test (Section III-A, Figure 2).

:func:`orthographic_orbit` looks at the person's centre from a circle of ``radius_m`` at ``altitude_m``
turning at ``angular_velocity_deg_s`` and projects orthographically (scaled by focal / distance so that
image sizes match the perspective camera), then adds the detector errors of
:func:`reconstruction.synth.synthesize_capture` (Gaussian noise, outliers in the person's box grown by
50 %, whole-detection left/right swaps, misses). The perspective case is ``reconstruction.synth`` itself.
"""

from __future__ import annotations

import numpy as np

from reconstruction.synth import look_at_T_world_cam
from skycap.frames import intrinsics_matrix
from skycap.skeleton import COCO17_FLIP

__all__ = ["orthographic_orbit"]


def orthographic_orbit(joints_ned_m: np.ndarray, setup, width_px: int = 1920, height_px: int = 1080):
    """Observe joints (T, 17, 3) sampled at ``setup.fps``.

    ``setup``: an object with angular_velocity_deg_s, radius_m, altitude_m, focal_px, fps, noise_px,
    outlier_rate, swap_rate, miss_rate, seed (:class:`reconstruction.monocular.evaluate.EvalSetup`).
    Returns W_px (T, 2, 17) (NaN where missing), confidence (T, 17), T_world_cam (T, 4, 4), K (3, 3).
    """
    J = np.asarray(joints_ned_m, dtype=float)
    T = J.shape[0]
    rng = np.random.default_rng(setup.seed)
    centre = J.mean(axis=1)
    ang = np.radians(setup.angular_velocity_deg_s) * np.arange(T) / setup.fps
    cam = np.stack([centre[:, 0] + setup.radius_m * np.cos(ang), centre[:, 1] + setup.radius_m * np.sin(ang),
                    np.full(T, -setup.altitude_m)], axis=-1)  # fmt: skip
    T_wc = look_at_T_world_cam(cam, centre)
    K = intrinsics_matrix(setup.focal_px, setup.focal_px, width_px / 2.0, height_px / 2.0)
    R_cw = np.swapaxes(T_wc[:, :3, :3], 1, 2)
    dist = np.linalg.norm(cam - centre, axis=-1)
    pc = np.einsum("tij,tkj->tki", R_cw, J - centre[:, None])
    uv = setup.focal_px * pc[..., :2] / dist[:, None, None] + K[:2, 2]  # (T,17,2)
    lo, hi = uv.min(1), uv.max(1)
    span = np.maximum(hi - lo, 20.0)
    uv = uv + rng.normal(0.0, setup.noise_px, uv.shape)
    conf = rng.uniform(0.5, 1.0, (T, 17))
    out = rng.random((T, 17)) < setup.outlier_rate
    rnd = (lo - 0.25 * span)[:, None] + rng.random((T, 17, 2)) * (1.5 * span)[:, None]
    uv = np.where(out[..., None], rnd, uv)
    conf = np.where(out, rng.uniform(0.2, 0.8, (T, 17)), conf)
    swap = rng.random(T) < setup.swap_rate
    uv[swap] = uv[swap][:, list(COCO17_FLIP)]
    conf[swap] = conf[swap][:, list(COCO17_FLIP)]
    miss = rng.random((T, 17)) < setup.miss_rate
    conf[miss] = 0.0
    W = np.swapaxes(uv, 1, 2)
    W = np.where((conf > 0)[:, None, :], W, np.nan)
    return W, conf, T_wc, K
