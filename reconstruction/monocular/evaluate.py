"""Evaluation of the monocular method on real motion capture seen by one virtual orbiting drone.

:func:`evaluate_clip` takes COCO-17 ground truth from a BVH file, flies one virtual drone around it with
:func:`reconstruction.synth.synthesize_capture` (perspective camera, noisy 2D keypoints with outliers,
swaps and misses, drone-estimated camera poses) or, with ``camera = "orthographic"``, the orthographic
camera of the paper's synthetic test (:mod:`reconstruction.monocular.orbit`), runs the pipeline and scores
PA-MPJPE (mean joint distance after the best per-frame similarity transform) on the 12 limb joints
(DroCap's joints) for the initialisation, the BA, the BA without articulation and the extended BA.

:func:`sweep` repeats this over orbit angular velocities and draws DroCap's Figure 2.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path

import numpy as np

from reconstruction.metrics import BODY_GROUPS, accuracy_metrics, pa_mpjpe_mm, per_joint_errors_mm, w_mpjpe_mm
from reconstruction.monocular.dictionary import PoseDictionary, load_dictionary
from reconstruction.monocular.pipeline import MonocularConfig, reconstruct_monocular, to_world_metric
from skycap.bvh import read_bvh
from skycap.errors import SkycapError
from skycap.skeleton import JOINT_GROUPS, mocap_to_coco17

log = logging.getLogger(__name__)

__all__ = ["EvalSetup", "EvalMonocularConfig", "load_motion", "make_view", "evaluate_clip", "sweep", "plot_sweep"]

#: DroCap's 12 evaluated joints (shoulders, elbows, wrists, hips, knees, ankles).
LIMB_JOINTS: tuple[int, ...] = (5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16)


@dataclasses.dataclass
class EvalSetup:
    """The virtual flight and the 2D detector noise."""

    angular_velocity_deg_s: float = 25.0  # DroCap's drone: about 25 deg/s
    radius_m: float = 4.0
    altitude_m: float = 2.0  # camera height above the ground
    camera: str = "perspective"  # synthetic camera: "perspective" (reconstruction.synth) or "orthographic"
    focal_px: float = 1500.0
    noise_px: float = 5.0
    outlier_rate: float = 0.10
    swap_rate: float = 0.0
    miss_rate: float = 0.0
    fps: float = 24.0
    clip_seconds: float = 10.0  # first seconds of the clip (after the T-pose frame)
    camera_rot_noise_deg: float = 2.0  # drone attitude error (extended BA's prior, perspective BA)
    camera_pos_noise_m: float = 0.5  # drone position error, RMS (perspective BA); synth's default GPS error
    camera_noise_drift_fraction: float = 0.0  # share of the pose error's variance that drifts slowly (rest white)
    seed: int = 0


@dataclasses.dataclass
class EvalMonocularConfig:
    setup: EvalSetup = dataclasses.field(default_factory=EvalSetup)
    method: MonocularConfig = dataclasses.field(default_factory=MonocularConfig)
    extended: bool = True  # also run the extended BA (beyond the paper)
    perspective: bool = True  # also run the perspective BA with the drone's camera poses (beyond the paper)
    dictionary: str = ""  # pose dictionary npz ("" = the shipped one)


@dataclasses.dataclass
class View:
    W_px: np.ndarray  # (T, 2, 17)
    confidence: np.ndarray  # (T, 17)
    T_world_cam: np.ndarray  # (T, 4, 4) drone-estimated
    K: np.ndarray  # (3, 3)
    gt_ned_m: np.ndarray  # (T, 17, 3) ground truth at the frames
    t_ns: np.ndarray  # (T,)


def load_motion(path: str | Path, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth COCO-17 joints (T, 17, 3) NED metres and times (T,) ns of the first ``seconds``."""
    p = Path(path)
    if not p.is_file():
        raise SkycapError(f"motion file {p} does not exist; pass a CMU CC_Base BVH file to --motion")
    m = read_bvh(p)
    n = min(m.num_frames - 1, int(round(seconds * m.fps)) + 1)
    if n < 10:
        raise SkycapError(f"motion file {p} has only {m.num_frames} frames; need at least 11")
    J = mocap_to_coco17(m.slice(1, 1 + n))
    t_ns = (np.arange(n) * m.frame_time_s * 1e9).astype(np.int64)
    return J, t_ns


def make_view(joints_ned: np.ndarray, t_ns: np.ndarray, setup: EvalSetup) -> View:
    """One virtual orbiting drone's observations of the motion."""
    if setup.camera == "perspective":
        from reconstruction.synth import SynthConfig, interpolate_joints, synthesize_capture

        sc = SynthConfig(
            drones=1, radius_m=setup.radius_m, altitude_m=setup.altitude_m,
            speed_mps=np.radians(setup.angular_velocity_deg_s) * setup.radius_m, camera_rate_hz=setup.fps,
            unsync=False, noise_px=setup.noise_px, outlier_rate=setup.outlier_rate, swap_rate=setup.swap_rate,
            miss_rate=setup.miss_rate, camera_pos_noise_m=setup.camera_pos_noise_m,
            camera_noise_drift_fraction=setup.camera_noise_drift_fraction, camera_rot_noise_deg=setup.camera_rot_noise_deg,
            focal_px=setup.focal_px,
        )  # fmt: skip
        cap, truth = synthesize_capture(joints_ned, t_ns, sc, seed=setup.seed)
        cam = cap.cameras[0]
        conf = cam.confidence[:, 0]
        W = np.swapaxes(cam.keypoints_px[:, 0], 1, 2).copy()
        W = np.where((conf > 0)[:, None, :], W, np.nan)
        gt = interpolate_joints(truth.t_ns, truth.joints_ned, cam.t_frame_ns)
        return View(W, conf, cam.pose_at(cam.t_frame_ns), cam.K[0], gt, cam.t_frame_ns)
    if setup.camera == "orthographic":
        from reconstruction.monocular.orbit import orthographic_orbit
        from reconstruction.synth import interpolate_joints

        tf = np.arange(t_ns[0], t_ns[-1] + 1, int(1e9 / setup.fps), dtype=np.int64)
        gt = interpolate_joints(t_ns, joints_ned, tf)
        W, conf, T_wc, K = orthographic_orbit(gt, setup)
        return View(W, conf, T_wc, K, gt, tf)
    raise SkycapError(f"setup.camera must be 'perspective' or 'orthographic', not {setup.camera!r}")


def _score(S: np.ndarray, gt: np.ndarray) -> tuple[float, dict]:
    pred = np.swapaxes(S, 1, 2)
    e = per_joint_errors_mm(pred[:, list(LIMB_JOINTS)], gt[:, list(LIMB_JOINTS)], aligned=True).mean(0)
    per = dict(zip(LIMB_JOINTS, e))
    groups = {g: float(np.mean([per[j] for j in js])) for g, js in JOINT_GROUPS.items() if all(j in per for j in js)}
    return float(pa_mpjpe_mm(pred, gt, joints=LIMB_JOINTS)), groups


def evaluate_clip(motion: str | Path, cfg: EvalMonocularConfig, dictionary: PoseDictionary | None = None) -> dict:
    """Metrics (dict, JSON-able) of the pipeline on one motion file under ``cfg``."""
    d = dictionary or load_dictionary(cfg.dictionary or None)
    J, t_ns = load_motion(motion, cfg.setup.clip_seconds)
    view = make_view(J, t_ns, cfg.setup)
    t0 = time.perf_counter()
    dt_s = float(np.median(np.diff(view.t_ns))) * 1e-9 if len(view.t_ns) > 1 else 1.0 / cfg.setup.fps
    res = reconstruct_monocular(view.W_px, view.confidence, d, cfg.method, T_world_cam=view.T_world_cam, extended=cfg.extended,
                                K=view.K, perspective=cfg.perspective, dt_s=dt_s, t_ns=view.t_ns)  # fmt: skip
    total = time.perf_counter() - t0
    out: dict = {"motion": str(motion), "frames": int(view.W_px.shape[0])}
    out["pa_mpjpe_mm_init"], out["per_joint_mm_init"] = _score(res.init.S, view.gt_ned_m)
    out["pa_mpjpe_mm_ba"], out["per_joint_mm"] = _score(res.ba.S, view.gt_ned_m)
    if res.ba_no_articulation is not None:
        out["pa_mpjpe_mm_ba_no_articulation"], _ = _score(res.ba_no_articulation.S, view.gt_ned_m)
    out["ba_warmup_accepted"] = res.ba.warmup_accepted
    if res.ba_paper is not None:
        out["pa_mpjpe_mm_ba_paper_order"], _ = _score(res.ba_paper.S, view.gt_ned_m)
    if res.ba_extended is not None:
        out["pa_mpjpe_mm_ba_extended"], out["per_joint_mm_extended"] = _score(res.ba_extended.S, view.gt_ned_m)
    if res.ba_extended is not None and cfg.perspective:
        # the extended BA placed in the world the rough way (assumed body size, depth from the image size)
        Xr = to_world_metric(res.ba_extended.S, res.ba_extended.R, view.W_px, res.weights, view.T_world_cam, view.K,
                             cfg.method.perspective.body_rms_radius_m, frame=res.ba_extended_frame)  # fmt: skip
        out["w_mpjpe_mm_ba_extended_rough"] = float(w_mpjpe_mm(Xr, view.gt_ned_m, joints=LIMB_JOINTS))
    if res.lifted is not None:
        out["pa_mpjpe_mm_lifted"], out["per_joint_mm_lifted"] = _score(res.lifted.S, view.gt_ned_m)
        out["lifted_seconds"] = res.lifted_seconds
    if res.ba_perspective is not None:
        out["perspective_start"] = res.perspective_start
        Xp = res.ba_perspective.X
        out["pa_mpjpe_mm_ba_perspective"], out["per_joint_mm_perspective"] = _score(np.swapaxes(Xp, 1, 2), view.gt_ned_m)
        out["w_mpjpe_mm_ba_perspective"] = float(w_mpjpe_mm(Xp, view.gt_ned_m, joints=LIMB_JOINTS))
        out["perspective_seconds"] = res.perspective_seconds
        out["perspective_iterations"] = res.ba_perspective.iterations
    if res.model is not None:
        Xm = res.model.joints_ned
        out["pa_mpjpe_mm_model"], out["per_joint_mm_model"] = _score(np.swapaxes(Xm, 1, 2), view.gt_ned_m)
        out["w_mpjpe_mm_model"] = float(w_mpjpe_mm(Xm, view.gt_ned_m, joints=LIMB_JOINTS))
        # the product output's figures named as everywhere (reconstruction.metrics), over the 12 limb joints
        limb_groups = {g: js for g, js in BODY_GROUPS.items() if set(js) <= set(LIMB_JOINTS)}
        out["model_accuracy"] = accuracy_metrics(Xm, view.gt_ned_m, LIMB_JOINTS, groups=limb_groups, ndigits=None)
        out["model_seconds"] = res.model_seconds
        out["model_start"] = res.model_start
    out["init_seconds"] = res.init_seconds
    out["ba_seconds"] = res.ba_seconds
    out["total_seconds"] = total
    out["ba_outer_iterations"] = int(len(res.ba.objective) - 1)
    out["weights_zero_fraction"] = float(np.mean(res.weights <= 0))
    return out


def sweep(motions: list, cfg: EvalMonocularConfig, omegas_deg_s: list[float], progress: bool = True) -> list[dict]:
    """Evaluate every motion at every angular velocity. Returns one row per (motion, omega)."""
    from tqdm import tqdm

    d = load_dictionary(cfg.dictionary or None)
    rows = []
    jobs = [(m, w) for w in omegas_deg_s for m in motions]
    for m, w in tqdm(jobs, disable=not progress, desc="sweep"):
        c = dataclasses.replace(cfg, setup=dataclasses.replace(cfg.setup, angular_velocity_deg_s=float(w)))
        r = evaluate_clip(m, c, d)
        r["angular_velocity_deg_s"] = float(w)
        rows.append(r)
        log.info("%s @ %g deg/s: init %.1f BA %.1f BA-no-art %.1f", Path(m).stem, w, r["pa_mpjpe_mm_init"], r["pa_mpjpe_mm_ba"],
                 r.get("pa_mpjpe_mm_ba_no_articulation", np.nan))  # fmt: skip
    return rows


def sweep_means(rows: list[dict]) -> dict:
    """Mean over motions per angular velocity: {key: (omegas, values)}."""
    omegas = sorted({r["angular_velocity_deg_s"] for r in rows})
    keys = ["pa_mpjpe_mm_init", "pa_mpjpe_mm_ba", "pa_mpjpe_mm_ba_paper_order", "pa_mpjpe_mm_ba_no_articulation",
            "pa_mpjpe_mm_ba_extended", "pa_mpjpe_mm_lifted",
            "pa_mpjpe_mm_ba_perspective", "w_mpjpe_mm_ba_perspective", "pa_mpjpe_mm_model", "w_mpjpe_mm_model"]
    out = {"angular_velocity_deg_s": omegas}
    for k in keys:
        vals = [[r[k] for r in rows if r["angular_velocity_deg_s"] == w and k in r] for w in omegas]
        if all(vals):
            out[k] = [float(np.mean(v)) for v in vals]
    return out


def plot_sweep(means: dict, path: str | Path, title: str = "") -> Path:
    """DroCap Figure 2: error vs camera angular velocity for Initial, BA, BA w/o art. (+ extended)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4))
    w = means["angular_velocity_deg_s"]
    for k, lab, st in [
        ("pa_mpjpe_mm_init", "Initial", "o--"),
        ("pa_mpjpe_mm_ba_no_articulation", "BA w/o art.", "s-"),
        ("pa_mpjpe_mm_ba_paper_order", "BA (paper's update order)", "x--"),
        ("pa_mpjpe_mm_ba", "BA (articulation warm-up)", "^-"),
        ("pa_mpjpe_mm_ba_extended", "BA extended (ours)", "d:"),
        ("pa_mpjpe_mm_lifted", "learned single-frame lift (ours)", "*:"),
        ("pa_mpjpe_mm_ba_perspective", "BA perspective, known cameras (ours)", "v-"),
        ("pa_mpjpe_mm_model", "body model after BA perspective (ours)", "P-"),
    ]:
        if k in means:
            ax.plot(w, means[k], st, label=lab)
    ax.set_xlabel("camera angular velocity (deg/s)")
    ax.set_ylabel("reconstruction error (mm, PA-MPJPE)")
    ax.grid(alpha=0.3)
    ax.legend()
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, dpi=120)
    plt.close(fig)
    return p


def write_json(path: str | Path, data) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(data, indent=2, default=float))
    return p
