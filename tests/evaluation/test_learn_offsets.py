"""evaluation.learn_offsets.solve_offsets: cameras seeing a detector's offset points (noise, outliers) -> the
offsets back in the body frame, whatever way the person faces."""

import numpy as np

from evaluation.learn_offsets import solve_offsets
from reconstruction.multiview.offsets import apply_offsets, body_frame
from reconstruction.synth import look_at_T_world_cam, procedural_walker


def test_solve_offsets_recovers_a_convention_from_2d():
    rng = np.random.default_rng(0)
    J, *_ = procedural_walker(30)
    yaw = np.linspace(0, 2 * np.pi, len(J))  # the person turns: the offsets must be in the body frame
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.stack([np.stack([c, -s, 0 * c], -1), np.stack([s, c, 0 * c], -1), np.stack([0 * c, 0 * c, 1 + 0 * c], -1)], -2)
    ctr = J.mean(1, keepdims=True)
    J = np.einsum("tij,tnj->tni", Rz, J - ctr) + ctr
    true = rng.normal(0, 0.04, (17, 3))
    Xo = apply_offsets(J, true)
    K = np.array([[1000.0, 0, 640], [0, 1000.0, 360], [0, 0, 1]])
    obs = {k: [] for k in ("joint", "uv", "conf", "J", "R_body", "R_wc", "p_wc", "K")}
    Rb = body_frame(J)
    for a in np.radians([0, 120, 240]):
        pos = ctr[:, 0] + np.array([8 * np.cos(a), 8 * np.sin(a), -6.0])
        for t in range(len(J)):
            T = look_at_T_world_cam(pos[t], ctr[t, 0])
            pc = (Xo[t] - T[:3, 3]) @ T[:3, :3]
            uv = pc[:, :2] / pc[:, 2:] * 1000.0 + [640, 360] + rng.normal(0, 2.0, (17, 2))
            bad = rng.random(17) < 0.05
            uv[bad] += rng.normal(0, 60.0, (bad.sum(), 2))  # outliers
            obs["joint"].append(np.arange(17))
            obs["uv"].append(uv)
            obs["conf"].append(np.full(17, 0.8))
            obs["J"].append(J[t])
            obs["R_body"].append(np.repeat(Rb[t][None], 17, 0))
            obs["R_wc"].append(np.repeat(T[None, :3, :3], 17, 0))
            obs["p_wc"].append(np.repeat(T[None, :3, 3], 17, 0))
            obs["K"].append(np.repeat(K[None], 17, 0))
    obs = {k: np.concatenate(v) for k, v in obs.items()}
    off, stats = solve_offsets(obs)
    assert np.abs(off - true).max() < 0.010, np.abs(off - true).max(1)
    assert stats["left_shoulder"]["median_px_after"] < stats["left_shoulder"]["median_px_before"] or \
        np.linalg.norm(true[5]) < 0.01
