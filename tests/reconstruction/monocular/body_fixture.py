"""Shared test data of the monocular tests."""

import numpy as np

#: an upright adult-sized T-ish body (COCO-17, body frame x forward, y right, z down; metres), feet at z = 0
UPRIGHT_BODY = np.array([
    [0.10, 0.00, -1.65], [0.12, -0.04, -1.68], [0.12, 0.04, -1.68], [0.05, -0.08, -1.66], [0.05, 0.08, -1.66],
    [0.00, -0.19, -1.45], [0.00, 0.19, -1.45], [0.05, -0.30, -1.18], [-0.05, 0.30, -1.18],
    [0.15, -0.33, -0.95], [0.05, 0.36, -0.93], [0.00, -0.10, -0.95], [0.00, 0.10, -0.95],
    [0.10, -0.11, -0.50], [-0.05, 0.11, -0.50], [0.00, -0.12, -0.05], [-0.10, 0.12, -0.05],
])  # fmt: skip


def orbit_view(X: np.ndarray, t_s: np.ndarray, omega_deg_s: float = 30.0):
    """Noise-free keypoints of joints X (T, 17, 3) NED seen by a camera orbiting their centre (4 m out, 2 m up)
    at ``omega_deg_s``: (W_px (T, 2, 17), T_world_cam (T, 4, 4), K (3, 3))."""
    from reconstruction.synth import look_at_T_world_cam
    from skycap.frames import intrinsics_matrix

    T = len(X)
    centre = X.mean(1)
    ang = np.radians(omega_deg_s) * t_s
    cam = np.stack([centre[:, 0] + 4 * np.cos(ang), centre[:, 1] + 4 * np.sin(ang), np.full(T, -2.0)], -1)
    T_wc = look_at_T_world_cam(cam, centre)
    K = intrinsics_matrix(1500.0, 1500.0, 960.0, 540.0)
    Xc = np.einsum("tji,tkj->tki", T_wc[:, :3, :3], X - T_wc[:, None, :3, 3])
    uv = 1500.0 * Xc[..., :2] / Xc[..., 2:3] + np.array([960.0, 540.0])
    return np.swapaxes(uv, 1, 2), T_wc, K
