"""The multi-view evaluation harness: real motion -> virtual drones -> noisy capture -> fit -> metrics.

Ground truth: the BVH's COCO-17 joints from :func:`skycap.skeleton.mocap_to_coco17` (CMU CC_Base rig
joint -> COCO-17 mapping documented in :mod:`skycap.skeleton`: shoulders = ``*_Upperarm``, elbows =
``*_Forearm``, wrists = ``*_Hand``, hips = ``*_Thigh``, knees = ``*_Calf``, ankles = ``*_Foot``, eyes =
``*_Eye``, nose/ears at fixed offsets in the head frame), first (T-pose) frame skipped. Scored joints:
:data:`skycap.skeleton.SCORED_JOINTS` (12 limb joints + nose as the head).

Output times: every ``round(bvh_fps / camera_rate_hz)``-th mocap frame from ``start`` (in output
frames), ``frames`` of them; the GT there is exact (no interpolation); the cameras are not synchronised
to them.

Metrics (``metrics.json``, named as in :mod:`reconstruction.metrics`): ``mpjpe_mm`` (root-aligned: mid-hip
subtracted, Human3.6M protocol 1), ``pa_mpjpe_mm`` (per-frame similarity Procrustes, protocol 2), ``w_mpjpe_mm``
(world, no alignment), ``root_err_mm``, ``per_group_mm`` {torso / arms / legs / head: {mpjpe_mm, pa_mpjpe_mm,
w_mpjpe_mm}}, ``keypoints_source`` and ``position_grade`` (what the 2D keypoints and the drone poses were),
``per_joint`` {group: {position_mm (world),
angle_deg}} as AirCap Table 1 (angle = angle between estimated and true direction of the bone leaving
the joint: shoulder->elbow, elbow->wrist, hip->knee, knee->ankle; for wrist and ankle the bone into
it; head: mid-shoulder->nose), camera position/rotation error of the drone estimates (``_before``) and
of the refined poses (``_after``) over the frames the method used, ``frames``, ``fit_seconds``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from reconstruction.capture import interpolate_poses
from reconstruction.metrics import accuracy_metrics, per_joint_errors_mm
from reconstruction.multiview.fit import FitConfig, FitResult, fit_capture
from reconstruction.synth import SynthConfig, SynthTruth, synthesize_capture
from skycap.bvh import read_bvh
from skycap.errors import SkycapError
from skycap.skeleton import JOINT_GROUPS, SCORED_JOINTS, mocap_to_coco17

log = logging.getLogger(__name__)

#: joint -> (from, to) of the bone whose direction error is that joint's angle error (COCO-17 indices)
ANGLE_BONES = {5: (5, 7), 6: (6, 8), 7: (7, 9), 8: (8, 10), 9: (7, 9), 10: (8, 10),
               11: (11, 13), 12: (12, 14), 13: (13, 15), 14: (14, 16), 15: (13, 15), 16: (14, 16)}  # fmt: skip


@dataclasses.dataclass
class EvalConfig:
    motion: str = ""
    out: str = ""
    frames: int = 300  # output frames (0 = all)
    start: int = 0  # first output frame
    seed: int = 0
    export: bool = True
    synth: SynthConfig = dataclasses.field(default_factory=SynthConfig)
    fit: FitConfig = dataclasses.field(default_factory=FitConfig)


def load_motion(path: str | Path) -> tuple[np.ndarray, np.ndarray, float]:
    """(joints (T, 17, 3) NED m, t_ns (T,), fps) of a CC_Base BVH, T-pose frame skipped."""
    m = read_bvh(path)
    if m.num_frames < 3:
        raise SkycapError(f"{path}: needs at least 3 frames")
    m = m.slice(1)
    J = mocap_to_coco17(m)
    t_ns = np.round(np.arange(m.num_frames) * m.frame_time_s * 1e9).astype(np.int64)
    return J, t_ns, m.fps


def bone_angle_errors_deg(pred: np.ndarray, gt: np.ndarray) -> dict[int, np.ndarray]:
    """Per joint (COCO index) the per-frame angle (deg) between estimated and true bone directions."""
    out = {}
    pairs = dict(ANGLE_BONES)
    for j, (a, b) in pairs.items():
        u, v = pred[:, b] - pred[:, a], gt[:, b] - gt[:, a]
        c = np.sum(u * v, -1) / np.maximum(np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1), 1e-12)
        out[j] = np.degrees(np.arccos(np.clip(c, -1, 1)))
    neck_p, neck_g = 0.5 * (pred[:, 5] + pred[:, 6]), 0.5 * (gt[:, 5] + gt[:, 6])
    u, v = pred[:, 0] - neck_p, gt[:, 0] - neck_g
    c = np.sum(u * v, -1) / np.maximum(np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1), 1e-12)
    out[0] = np.degrees(np.arccos(np.clip(c, -1, 1)))
    return out


def camera_errors(res: FitResult, capture, truth: SynthTruth) -> dict[str, float]:
    """Mean position (m) and rotation (deg) errors of drone-estimated and refined camera poses."""
    pb, pa, rb, ra = [], [], [], []
    for ci, cam in enumerate(capture.cameras):
        sel = res.cam_index == ci
        if not np.any(sel):
            continue
        Tt = interpolate_poses(cam.t_pose_ns, truth.T_world_cam_true[ci], res.cam_t_ns[sel])
        for T_est, P, Rl in ((res.T_world_cam_drone[sel], pb, rb), (res.T_world_cam_refined[sel], pa, ra)):
            P.append(np.linalg.norm(T_est[:, :3, 3] - Tt[:, :3, 3], axis=-1))
            Rl.append(Rotation.from_matrix(np.swapaxes(Tt[:, :3, :3], -1, -2) @ T_est[:, :3, :3]).magnitude())
    c = np.concatenate
    return {
        "camera_pos_err_m_before": float(c(pb).mean()), "camera_pos_err_m_after": float(c(pa).mean()),
        "camera_rot_err_deg_before": float(np.degrees(c(rb).mean())), "camera_rot_err_deg_after": float(np.degrees(c(ra).mean())),
    }  # fmt: skip


def compute_metrics(res: FitResult, gt: np.ndarray) -> dict:
    pred = res.joints_ned
    e = per_joint_errors_mm(pred, gt)
    ang = bone_angle_errors_deg(pred, gt)
    per_joint = {
        g: {"position_mm": float(e[:, list(idx)].mean()), "angle_deg": float(np.mean([ang[j].mean() for j in idx]))}
        for g, idx in JOINT_GROUPS.items()
    }
    return {**accuracy_metrics(pred, gt, SCORED_JOINTS, ndigits=None), "per_joint": per_joint}


def sources(synth: SynthConfig) -> dict:
    """What the harness scored: ``keypoints_source`` (the 2D keypoints) and ``position_grade`` (the drone poses), with
    their details (``keypoints_detail``, ``pose_errors_detail``). This harness's keypoints are simulated ("sim");
    its poses carry white noise ("white") or the flight's model ("flight": :mod:`evaluation.harness` names the
    grade, rtk or gps)."""
    drift = f", drift fraction {synth.camera_noise_drift_fraction:g}" if synth.camera_noise_drift_fraction else ""
    if synth.pose_errors == "flight":
        fe = synth.flight_errors
        pose = (f"Gauss-Markov position bias {fe.pos_bias_std_xy_m:g} m horizontal / {fe.pos_bias_std_z_m:g} m vertical "
                f"(tau {fe.pos_bias_time_constant_s:g} s) + {fe.pos_noise_std_m:g} m white; attitude "
                f"{fe.att_noise_std_deg:g} deg per axis (tau {fe.att_noise_time_constant_s:g} s)")
    else:
        pose = f"white noise {synth.camera_pos_noise_m:g} m / {synth.camera_rot_noise_deg:g} deg{drift}"
    return {"keypoints_source": "sim", "position_grade": "flight" if synth.pose_errors == "flight" else "white",
            "keypoints_detail": f"simulated: true projections + {synth.noise_px:g} px noise, "
                                f"{100 * synth.outlier_rate:g} % outliers ({synth.detectors} detector(s))",
            "pose_errors_detail": pose}


def clip_indices(num_frames: int, fps: float, camera_rate_hz: float, start: int, frames: int, motion: str = "") -> np.ndarray:
    """The scored mocap frames: every ``round(fps / camera_rate_hz)``-th from output frame ``start``, ``frames`` of them
    (0 = all)."""
    step = max(1, int(round(fps / camera_rate_hz)))
    idx = np.arange(start * step, num_frames, step)
    if frames > 0:
        idx = idx[:frames]
    if len(idx) < 3:
        raise SkycapError(f"{motion}: only {len(idx)} output frames after --start {start}; use a longer clip or a smaller --start")
    return idx


def score_capture(cap, truth: SynthTruth, t_grid: np.ndarray, gt: np.ndarray, fit: FitConfig, motion: str = "",
                  progress: bool = True, scored: np.ndarray | None = None) -> tuple[FitResult, dict]:
    """Fit ``cap`` at the output times ``t_grid`` (T,) and score it against ``gt`` (S, 17, 3), the truth at the scored
    times ``t_grid[scored]`` (``scored``: (T,) bool, default all; the rest is context the fit sees but the metrics
    leave out): (fit result over all of ``t_grid``, metrics without the sources)."""
    res = fit_capture(cap, t_grid, fit, progress=progress)
    scored = np.ones(len(t_grid), bool) if scored is None else np.asarray(scored, bool)
    n = int(scored.sum())
    metrics = {"motion": str(motion), "method": fit.method, "frames": n, "cameras": cap.num_cameras,
               "context_frames": int(len(t_grid) - n), "fit_seconds": res.fit_seconds,
               "fit_frames_per_s": len(t_grid) / res.fit_seconds}  # fmt: skip
    metrics.update(compute_metrics(dataclasses.replace(res, joints_ned=res.joints_ned[scored], t_ns=res.t_ns[scored]), gt))
    metrics.update(camera_errors(res, cap, truth))
    return res, metrics


def write_outputs(out: str | Path, cfg, metrics: dict, res: FitResult, cap, t_grid: np.ndarray, gt: np.ndarray,
                  export: bool = True) -> Path:
    """``out``/config.toml (``cfg``), metrics.json and, with ``export``, the reconstruction's exports and the truth."""
    from reconstruction.export import export_motion
    from skycap.config import save_config

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.toml")
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    if export:
        cams = []
        for ci, cam in enumerate(cap.cameras):
            sel = res.cam_index == ci
            cams.append({"name": cam.name, "t_ns": res.cam_t_ns[sel], "T_world_cam": res.T_world_cam_refined[sel],
                         "K": cam.K[0], "width_px": cam.width_px, "height_px": cam.height_px})  # fmt: skip
        export_motion(out, res.joints_ned, res.t_ns, params=res.params(), shape=res.shape, cameras=cams, capture=cap,
                      stem="reconstruction")  # fmt: skip
        np.savez_compressed(out / "ground_truth.npz", t_ns=t_grid, joints_ned=gt)
    return out


def run_eval(cfg: EvalConfig, progress: bool = True) -> dict:
    """Run the harness; writes ``cfg.out``/metrics.json (+ exports) when ``cfg.out`` is set. Returns the metrics."""
    J, t_ns, fps = load_motion(cfg.motion)
    idx = clip_indices(len(J), fps, cfg.synth.camera_rate_hz, cfg.start, cfg.frames, cfg.motion)
    lo, hi = idx[0], idx[-1] + 1
    cap, truth = synthesize_capture(J[lo:hi], t_ns[lo:hi], cfg.synth, seed=cfg.seed)
    t_grid, gt = t_ns[idx], J[idx]
    res, metrics = score_capture(cap, truth, t_grid, gt, cfg.fit, cfg.motion, progress)
    metrics.update(sources(cfg.synth))
    if cfg.out:
        write_outputs(cfg.out, cfg, metrics, res, cap, t_grid, gt, cfg.export)
    return metrics
