"""The monocular (one orbiting drone) pipeline of DroCap: 2D tracks -> single-frame init -> bundle adjustment.

:func:`reconstruct_monocular` runs, on one camera's 2D COCO-17 keypoints ``W_px`` (T, 2, 17):

1. track cleaning (:func:`reconstruction.monocular.tracks.temporal_outlier_mask`): keypoints that jump
   away from their temporal neighbours get zero weight;
2. single-frame initialisation (:func:`reconstruction.monocular.single_frame.initialise`), which also
   flags keypoints inconsistent with the dictionary pose as outliers;
3. multi-frame bundle adjustment (:func:`reconstruction.monocular.ba.bundle_adjust`), the paper's
   objective (``variant="paper"``; by default with the adaptive articulation warm-up of
   :class:`reconstruction.monocular.ba.BAConfig`; the paper's exact update order is ``BAConfig.paper()``,
   also run as an ablation) or the extended one (``variant="extended"``: temporal smoothness of
   poses and rotations, and, when the drone's camera attitude ``T_world_cam`` is given, a prior pulling
   R_t to it, with the poses expressed in the world frame);
4. optionally (``perspective=True``, needs the camera poses and intrinsics) the perspective BA of
   :mod:`reconstruction.monocular.perspective` in the world frame (NED metres), started from the paper-order
   BA, from the extended BA and (``MonocularConfig.lifter``, beyond the paper) from the learned single-frame lift
   of :mod:`reconstruction.monocular.lifter`, each placed in the world, keeping the lowest objective;
5. then (``MonocularConfig.model.enabled``, on by default when the perspective BA runs) the body model fitted to
   the keypoints with the drone's camera poses, started from the perspective BA: the multi-view product fit
   (:func:`reconstruction.multiview.fit.fit_capture`) with one camera -- the skeleton body model with one shape
   for the clip, the learned pose prior and joint limits, temporal smoothness, a robust 2D term with left/right
   swap handling -- which settles the depth ambiguities that the dictionary's sparse code leaves; Adam, then
   L-BFGS to convergence (:func:`model_fit`; result ``MonocularResult.model``). When the kept perspective BA is not
   the lifted start's, the body model is fitted from the lifted start's too -- its posture, with the hip path and
   body size of the kept one (``ModelFitConfig.lifted_placed_like_kept``: the perspective objective ranks the
   placements, the model energy the postures) -- and the lower energy is kept (``ModelFitConfig.also_from_lifted``;
   ``MonocularResult.model_start``).

Poses come back in the orthographic camera's pixel units; :func:`to_world_metric` places them in the
world (NED, metres) using the camera poses and an assumed body size.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import time

import numpy as np

from reconstruction.monocular.ba import BAConfig, BAResult, bundle_adjust, limb_index_arrays, squared_limb_lengths
from reconstruction.monocular.dictionary import PoseDictionary
from reconstruction.monocular.lifter import LifterConfig, PoseLifter
from reconstruction.monocular.linalg import complete_rotation
from reconstruction.monocular.perspective import (
    PerspectiveConfig,
    PerspectiveResult,
    orthographic_to_world,
    perspective_bundle_adjust,
)
from reconstruction.multiview.fit import FitConfig, FitResult
from skycap.errors import SkycapError
from skycap.skeleton import COCO17
from reconstruction.monocular.single_frame import InitConfig, InitResult, initialise
from reconstruction.monocular.tracks import temporal_outlier_mask, track_noise_px

log = logging.getLogger(__name__)

__all__ = ["TrackConfig", "ModelFitConfig", "MonocularConfig", "model_fit", "MonocularResult", "reconstruct_monocular", "to_world_metric"]


@dataclasses.dataclass
class TrackConfig:
    enabled: bool = True
    half_window: int = 3
    threshold_rel: float = 0.2
    noise_mult: float = 2.0  # flag threshold >= this x the tracks' typical jitter (small, far person)


@dataclasses.dataclass
class ExtensionConfig:
    """Beyond the paper (``variant = "extended"``)."""

    smooth_S: float = 0.5  # temporal smoothness of the poses (per frame^2, normalised units)
    smooth_R: float = 0.5  # temporal smoothness of the rotations
    rot_prior: float = 2.0  # weight of the drone-attitude prior on R_t (used when camera poses are known)


def _model_fit_defaults() -> FitConfig:
    # one view: the pose prior must settle what the image cannot (limb depth), so it weighs more than with
    # several views (0.1); the camera stays the drone's smoothed track (one view cannot correct it). 400 Adam steps
    # find the basin, 1000 L-BFGS iterations converge in it (Adam alone stops far from the minimum)
    return FitConfig(w_pose_prior=0.5, iters=400, refine_cameras=False, polish_iters=1000)


@dataclasses.dataclass
class ModelFitConfig:
    """Beyond the paper: the body model fitted after the perspective BA (step 5 of the module docstring)."""

    enabled: bool = True
    fit: FitConfig = dataclasses.field(default_factory=_model_fit_defaults)
    also_from_lifted: bool = True  # fit from the lifted start's perspective BA too; keep the lower energy
    lifted_placed_like_kept: bool = True  # ... with its hip path and body size taken from the kept perspective BA
    pos_sigma_m: float = 0.5  # the drone's camera position and attitude uncertainty (RMS 3D; used when the
    rot_sigma_deg: float = 2.0  # fit refines the camera, ``fit.refine_cameras``)


@dataclasses.dataclass
class MonocularConfig:
    tracks: TrackConfig = dataclasses.field(default_factory=TrackConfig)
    init: InitConfig = dataclasses.field(default_factory=InitConfig)
    ba: BAConfig = dataclasses.field(default_factory=BAConfig)
    extension: ExtensionConfig = dataclasses.field(default_factory=ExtensionConfig)
    perspective: PerspectiveConfig = dataclasses.field(default_factory=PerspectiveConfig)
    model: ModelFitConfig = dataclasses.field(default_factory=ModelFitConfig)
    lifter: LifterConfig = dataclasses.field(default_factory=LifterConfig)  # an extra start of the perspective BA
    #: which perspective BA the body model starts from: "lowest_objective" (of the starts run; then the model is also
    #: fitted from the lifted start, ``model.also_from_lifted``), or one start's name ("ba_paper", "ba_extended",
    #: "lifted": that start only, for ablations)
    perspective_start: str = "lowest_objective"
    ablation_no_articulation: bool = True  # also run BA with gamma = 0 (the paper's "BA w/o art.")
    ablation_paper_order: bool = True  # also run the paper's BA exactly (gamma from the start, L by SVD) when the
    # default BA differs from it (adaptive gamma warm-up, adult-proportion L; see BAConfig); the perspective BA
    # starts from it


@dataclasses.dataclass
class MonocularResult:
    init: InitResult
    ba: BAResult  # the paper's BA (gamma from config)
    ba_no_articulation: BAResult | None
    ba_extended: BAResult | None  # None unless requested
    weights: np.ndarray  # (T, J) weights used by BA
    init_seconds: float
    ba_seconds: float
    ba_extended_frame: str = "canonical"  # "world" when the attitude prior was used
    ba_perspective: PerspectiveResult | None = None  # world joints (needs camera poses and K)
    perspective_seconds: float = 0.0
    ba_paper: BAResult | None = None  # the paper's BA exactly (BAConfig.paper); None unless the default differs
    model: FitResult | None = None  # the body model fitted after the perspective BA (world joints and parameters)
    model_seconds: float = 0.0
    #: (T, 17) the confidence after track cleaning (what the body model fits; ``weights`` also has the init's inliers)
    confidence: np.ndarray | None = None
    lifted: InitResult | None = None  # the learned single-frame lift (beyond the paper); None unless it ran
    lifted_seconds: float = 0.0
    #: which start the kept perspective BA came from: "ba_paper", "ba_extended" or "lifted"
    perspective_start: str = ""
    model_start: str = ""  # which perspective BA the kept body model started from (lower model energy)


def _world_frame_start(init: InitResult, T_world_cam: np.ndarray):
    """Express the init in the world frame via the known camera rotations.

    The init gives camera coordinates ~ Rbar_t S_t (Rbar = R completed to 3x3); with R_cw the camera's
    world->camera rotation, S_world = R_cw^T Rbar S and R_t = R_cw[:2] reproduce the same image.
    """
    R_cw = np.swapaxes(T_world_cam[:, :3, :3], 1, 2)
    Rbar = complete_rotation(init.R)
    G = np.swapaxes(R_cw, 1, 2) @ Rbar
    S_world = G @ init.S
    return S_world, R_cw[:, :2, :].copy()


def _placed_like(X: np.ndarray, ref: np.ndarray, limbs) -> np.ndarray:
    """Joints X (T, 17, 3) moved and scaled to the placement of ``ref`` (T, 17, 3): per frame the hip centre of ref,
    one size for the clip (the median ratio of the RMS bone lengths); X's posture and orientation are kept."""
    a, b = limb_index_arrays(limbs)
    bones = lambda Y: np.sqrt(squared_limb_lengths(np.swapaxes(Y, 1, 2), a, b).mean(0))  # noqa: E731  (T,) RMS bone
    s = float(np.median(bones(ref) / np.maximum(bones(X), 1e-9)))
    hip = lambda Y: 0.5 * (Y[:, COCO17["left_hip"]] + Y[:, COCO17["right_hip"]])  # noqa: E731
    return hip(ref)[:, None] + s * (X - hip(X)[:, None])


@functools.lru_cache(maxsize=4)
def _lifter(path: str) -> PoseLifter:
    return PoseLifter.load(path or None)


def reconstruct_monocular(
    W_px: np.ndarray,
    confidence: np.ndarray | None,
    dictionary: PoseDictionary,
    cfg: MonocularConfig | None = None,
    T_world_cam: np.ndarray | None = None,
    extended: bool = False,
    K: np.ndarray | None = None,
    perspective: bool = False,
    dt_s: float = 1.0 / 24.0,
    t_ns: np.ndarray | None = None,
) -> MonocularResult:
    """Run the pipeline on one camera's keypoints.

    Args:
        W_px: (T, 2, 17) keypoints in pixels (NaN where missing).
        confidence: (T, 17) in [0, 1]; None = all ones.
        dictionary: the pose dictionary.
        T_world_cam: (T, 4, 4) the drone's camera poses at the frames (for the extended variant's prior).
        extended: also run the extended BA.
        K: (3, 3) or (T, 3, 3) intrinsics (for the perspective BA).
        perspective: also run the perspective BA in the world frame (needs ``T_world_cam`` and ``K``),
            started from the orthographic BAs placed in the world (:mod:`reconstruction.monocular.perspective`).
        dt_s: frame period (perspective BA's smoothness) when ``t_ns`` is not given.
        t_ns: (T,) frame times (ns): the perspective BA's smoothness then uses the true (uneven) intervals.
    """
    cfg = cfg or MonocularConfig()
    W_px = np.asarray(W_px, dtype=float)
    T = W_px.shape[0]
    conf = np.ones((T, W_px.shape[2])) if confidence is None else np.asarray(confidence, dtype=float).copy()
    conf = np.where(np.isfinite(W_px).all(1), conf, 0.0)
    noise_px = track_noise_px(W_px, conf, cfg.tracks.half_window) if T >= 3 else 0.0
    if cfg.tracks.enabled and T >= 3:
        flagged = temporal_outlier_mask(W_px, conf, cfg.tracks.half_window, cfg.tracks.threshold_rel, cfg.tracks.noise_mult)
        conf = conf * ~flagged
        log.info("track cleaning: %d of %d keypoints flagged (track jitter %.1f px)", int(flagged.sum()),
                 int((conf > 0).sum() + flagged.sum()), noise_px)  # fmt: skip
    lifter = _lifter(cfg.lifter.path) if perspective and cfg.lifter.enabled else None  # a bad path fails here, early
    t0 = time.perf_counter()
    init = initialise(W_px, conf, dictionary, cfg.init, noise_px=noise_px)
    init_s = time.perf_counter() - t0
    w = conf * init.inlier
    t0 = time.perf_counter()
    ba = bundle_adjust(W_px, w, init.S, init.R, dictionary.limbs, cfg.ba)
    ba_s = time.perf_counter() - t0
    ba0 = None
    if cfg.ablation_no_articulation:
        ba0 = bundle_adjust(W_px, w, init.S, init.R, dictionary.limbs, dataclasses.replace(cfg.ba, gamma=0.0))
    ba_paper = None
    paper_cfg = cfg.ba.paper_order()
    if cfg.ablation_paper_order and paper_cfg != cfg.ba:
        # a discarded warm-up already ran the paper's BA from the init (identical result)
        same = ba.warmup_accepted is False or (ba.warmup_accepted is None and cfg.ba.L_update == "svd")
        ba_paper = ba if same else bundle_adjust(W_px, w, init.S, init.R, dictionary.limbs, paper_cfg)
    ext, frame = None, "canonical"
    if extended:
        e = cfg.extension
        # the extended BA keeps the paper's update order (its figures were measured so; warm-up not tried there)
        bcfg = dataclasses.replace(paper_cfg, smooth_S=e.smooth_S, smooth_R=e.smooth_R)
        if T_world_cam is not None:
            S0, R_prior = _world_frame_start(init, np.asarray(T_world_cam, dtype=float))
            ext = bundle_adjust(
                W_px, w, S0, R_prior, dictionary.limbs, dataclasses.replace(bcfg, rot_prior=e.rot_prior), R_prior=R_prior
            )
            frame = "world"
        else:
            ext = bundle_adjust(W_px, w, init.S, init.R, dictionary.limbs, bcfg)
    persp, persp_s, persp_start, runs, model_start = None, 0.0, "", {}, ""
    lifted, lifted_s = None, 0.0
    if perspective:
        if T_world_cam is None or K is None:
            raise SkycapError("the perspective BA needs the camera poses T_world_cam (T, 4, 4) and intrinsics K; "
                              "pass them or run without perspective")  # fmt: skip
        t0 = time.perf_counter()
        T_wc = np.asarray(T_world_cam, dtype=float)
        Kf = np.asarray(K, dtype=float)
        pc = cfg.perspective
        place = dict(limbs=dictionary.limbs, bone_rms_m=pc.body_bone_rms_m)  # size from the bones: posture-free
        # from the paper-order BA (as measured: starting from the warm-up BA too, or instead, changed the kept
        # minimum on 002_05 by +1.4 to +1.7 mm PA and gained nothing on the mean; see results/RESULTS.md)
        b = ba_paper if ba_paper is not None else ba
        starts = {"ba_paper": orthographic_to_world(b.S, b.R, W_px, w, T_wc, Kf, pc.body_rms_radius_m, **place)}
        if ext is not None:
            starts["ba_extended"] = orthographic_to_world(ext.S, ext.R, W_px, w, T_wc, Kf, pc.body_rms_radius_m,
                                                          frame=frame, **place)  # fmt: skip
        if lifter is not None:
            t1 = time.perf_counter()
            lifted = lifter.lift(W_px, conf, cfg.lifter, noise_px=noise_px)
            lifted_s = time.perf_counter() - t1
            starts["lifted"] = orthographic_to_world(lifted.S, lifted.R, W_px, conf * lifted.inlier, T_wc, Kf,
                                                     pc.body_rms_radius_m, **place)  # fmt: skip
        # multi-start: keep the lowest objective (every run fits the same keypoints with the same weights)
        t_s = None if t_ns is None else (np.asarray(t_ns, dtype=np.int64) - int(t_ns[0])) * 1e-9
        runs = {k: perspective_bundle_adjust(W_px, w, T_wc, Kf, X0, dictionary.limbs, dt_s=dt_s, cfg=cfg.perspective, t_s=t_s)
                for k, X0 in starts.items()}  # fmt: skip
        if cfg.perspective_start == "lowest_objective":
            persp_start = min(runs, key=lambda k: runs[k].objective_final_sigma[1])
        elif cfg.perspective_start in runs:
            persp_start = cfg.perspective_start
        else:
            raise SkycapError(f"perspective_start {cfg.perspective_start!r} is not one of the starts run here "
                              f"({', '.join(['lowest_objective', *runs])}); pick one of those")  # fmt: skip
        persp = runs[persp_start]
        log.info("perspective BA: kept the start from %s (objectives %s)", persp_start,
                 ", ".join(f"{k} {r.objective_final_sigma[1]:.2f}" for k, r in runs.items()))  # fmt: skip
        persp_s = time.perf_counter() - t0
    model, model_s = None, 0.0
    if persp is not None and cfg.model.enabled:
        t0 = time.perf_counter()
        t_f = np.asarray(t_ns, dtype=np.int64) if t_ns is not None else np.round(np.arange(T) * dt_s * 1e9).astype(np.int64)
        fit = lambda X0: model_fit(W_px, conf, T_wc, Kf, t_f, X0, cfg.model)  # noqa: E731
        model, model_start = fit(persp.X), persp_start
        free = cfg.perspective_start == "lowest_objective"  # a named start is an ablation: that start only
        if cfg.model.also_from_lifted and free and "lifted" in runs and persp_start != "lifted":
            # the perspective BA's objective does not rank the starts' depths well; the body model's energy (its
            # pose prior and joint limits) does (results/RESULTS.md): fit from the lifted start too, keep the lower
            other = fit(_placed_like(runs["lifted"].X, persp.X, dictionary.limbs) if cfg.model.lifted_placed_like_kept else runs["lifted"].X)
            log.info("body model: energy %.3f from %s, %.3f from lifted", model.energy, persp_start, other.energy)
            if other.energy < model.energy:
                model, model_start = other, "lifted"
        model_s = time.perf_counter() - t0
    return MonocularResult(
        init=init, ba=ba, ba_no_articulation=ba0, ba_extended=ext, weights=w, init_seconds=init_s, ba_seconds=ba_s,
        ba_extended_frame=frame, ba_perspective=persp, perspective_seconds=persp_s, ba_paper=ba_paper,
        model=model, model_seconds=model_s, confidence=conf, lifted=lifted, lifted_seconds=lifted_s,
        perspective_start=persp_start, model_start=model_start,
    )  # fmt: skip


def model_fit(
    W_px: np.ndarray,
    confidence: np.ndarray,
    T_world_cam: np.ndarray,
    K: np.ndarray,
    t_ns: np.ndarray,
    X0: np.ndarray,
    cfg: ModelFitConfig | None = None,
) -> FitResult:
    """The body model fitted to one camera's keypoints, started from 3D joints (step 5 of the module docstring).

    Args:
        W_px: (T, 2, 17) keypoints in pixels (NaN where missing).
        confidence: (T, 17) in [0, 1] (0 where missing).
        T_world_cam: (T, 4, 4) the drone's camera poses at the frames (world NED).
        K: (3, 3) or (T, 3, 3) intrinsics.
        t_ns: (T,) frame times, increasing.
        X0: (T, 17, 3) the start (world NED metres), e.g. the perspective BA's joints.

    Returns the fit at the frame times (:class:`reconstruction.multiview.fit.FitResult`: joints, model
    parameters, the camera track used).
    """
    from reconstruction.capture import Capture, CameraCapture
    from reconstruction.multiview.fit import fit_capture

    cfg = cfg or ModelFitConfig()
    t_ns = np.asarray(t_ns, dtype=np.int64)
    T = len(t_ns)
    Kf = np.asarray(K, dtype=float)
    # one K for the clip (3, 3) or one per frame (T, 3, 3)
    t_K, Kf = (t_ns[:1], Kf[None]) if Kf.ndim == 2 else (t_ns, Kf)
    conf = np.where(np.isfinite(W_px).all(1), np.asarray(confidence, dtype=float), 0.0)
    cam = CameraCapture(
        name="camera", t_pose_ns=t_ns, T_world_cam=T_world_cam, pos_sigma_m=np.full(T, cfg.pos_sigma_m),
        rot_sigma_deg=np.full(T, cfg.rot_sigma_deg), t_intrinsics_ns=t_K, K=Kf, width_px=int(round(2 * Kf[0, 0, 2])),
        height_px=int(round(2 * Kf[0, 1, 2])), t_frame_ns=t_ns, keypoints_px=np.nan_to_num(np.swapaxes(W_px, 1, 2)),
        confidence=conf,
    )  # fmt: skip
    return fit_capture(Capture([cam]), t_ns, cfg.fit, progress=False, init_joints_ned=X0)


def to_world_metric(
    S_px: np.ndarray,
    R: np.ndarray,
    W_px: np.ndarray,
    weights: np.ndarray,
    T_world_cam: np.ndarray,
    K: np.ndarray,
    body_rms_radius_m: float,
    frame: str = "canonical",
) -> np.ndarray:
    """Place orthographic reconstructions in the world: joints (T, 17, 3) metres NED.

    The metric scale is not observable from one view, so each pose is scaled to the RMS radius
    ``body_rms_radius_m`` (e.g. the dictionary's mean); the depth of the body centre follows from the
    image size (depth = f * radius_m / radius_px, robust over time:
    :func:`reconstruction.monocular.perspective.robust_depth_track`), the centre lies on the ray through the
    weighted 2D centre, and the orientation comes from the camera's rotation (R completed to 3x3).
    """
    return orthographic_to_world(S_px, R, W_px, weights, T_world_cam, K, body_rms_radius_m, frame=frame)
