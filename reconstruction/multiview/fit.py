"""Multi-view body fitting: AirCap's per-frame objective (``method="paper"``) and the product's
whole-sequence fit (``method="product"``), both over any :class:`reconstruction.body.model.BodyModel`
with the learned :class:`reconstruction.prior.PosePrior`.

Paper path (AirCap, ICCV 2019, sec. 3.3 and 4.4), per output time t, independently:

    E = sum_{c,d,n} w^{n,d}_{c,t} rho_{sigma1}(|Pi(r_c, p_c, J_n(theta_t, beta_t)) - j^{n,d}_{c,t}|)
        + lambda_rp sum_c [rho_{sigma2}(|r_c - r~_c|) + rho_{sigma2}(|p_c - p~_c|)]
        + lambda_z E_prior(theta_t) + lambda_beta E_shape(beta_t)

with rho_s(e) = e^2 / (e^2 + s^2) (Geman-McClure), sigma1 = 40 px, sigma2 = 10 (read as 10 degrees
for the rotation vector and 10 cm for the position: the paper gives no unit), camera rotation vector
and position of every camera free per frame, the nearest-in-time frame of every camera, Adam with
1000 iterations at lr 0.25 for the first frame and 100 at lr 0.1 for each next one (warm-started from
the previous frame). Those learning rates were tuned for VPoser's unit-normal latent; our variables are
expressed in units that make the same rates give sensible steps (``paper_unit_*``: 0.1 rad for body
rotations, 0.1 m for the root, 1 cm for shape, 0.01 rad / 0.1 m for the cameras) -- in raw radians and
metres the schedule diverges. Our GMM prior's energy stands in for VPoser's |z| (no open VPoser exists); the
skeleton's shape energy for |beta|. The first frame starts from the robust triangulation (below), as
AirCap's online person estimate would.

Product path: all output times at once. Unknowns: pose, root orientation and root position per output
time, ONE shape for the person, and a pose correction (rotation vector, position) for EVERY camera
frame. Energy (negative log-likelihoods, summed, divided by the number of output times):

* data: each frame's keypoints against the body joints INTERPOLATED to the frame's capture time
  (cameras need no synchronisation), Geman-McClure with a scale annealed from 40 px to
  ``sigma_px_end``, weighted by confidence, normalised by the expected noise; for every detection the
  cheaper of the given and the left/right-swapped labelling counts (swap robustness);
* pose prior (GMM NLL) + joint-limit penalty; shape Mahalanobis to the population;
* temporal smoothness: joint accelerations / ``accel_sigma_mps2`` (all 17 joints, so root and pose);
* cameras: robust GPS/IMU prior on each frame's correction using the drones' own sigmas, and a
  motion-smoothness prior on the REFINED camera trajectory (position and rotation accelerations);
  when the capture carries the drones' velocity and angular velocity, the refined track's displacement
  and relative rotation between consecutive correction knots must match their integrals (with their
  noise integrated over the interval, and one gyro bias per camera): the pose samples' white noise then
  averages over the whole clip instead of over a knot interval;

initialised by robust triangulation (IRLS Geman-McClure over views), a shape measured on it, and
inverse kinematics; Adam (one-cycle learning rate) for ``iters`` steps, batched over the whole sequence on ``device``,
then optionally L-BFGS (``polish_iters``, :func:`lbfgs_polish`) at the final robust scale.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from reconstruction.body import skeleton17 as sk
from reconstruction.body.model import BodyModel, SkeletonBodyModel
from reconstruction.capture import Capture
from reconstruction.multiview.offsets import body_frame, body_frame_torch, load_offsets
from reconstruction.multiview.observations import camera_track, fill_gaps, gather, interpolate_to_grid, median_in_time, reject_blunders, triangulate
from reconstruction.optim import Adam, OneCycle
from reconstruction.prior import PosePrior, load_default_prior
from skycap.skeleton import COCO17_FLIP

log = logging.getLogger(__name__)

__all__ = ["FitConfig", "FitResult", "fit_capture", "initial_guess", "params_from_joints"]


@dataclasses.dataclass
class FitConfig:
    method: str = "product"  # "product" | "paper"
    device: str = "cpu"
    threads: int = 1  # torch CPU threads during the fit (small tensors: 1 is fastest; 0 = leave torch's)
    # paper path (AirCap)
    sigma1_px: float = 40.0
    sigma2: float = 10.0
    paper_first_iters: int = 1000
    paper_first_lr: float = 0.25
    paper_iters: int = 100
    paper_lr: float = 0.1
    paper_w_cam: float = 1.0
    paper_w_pose: float = 0.01
    paper_w_shape: float = 0.01
    # units of the paper path's free variables, so that AirCap's learning rates (0.25, 0.1 per Adam
    # step, tuned for VPoser's unit-normal latent) make steps of a sensible size for our parameters
    paper_unit_rot_rad: float = 0.1  # body pose and root orientation
    paper_unit_transl_m: float = 0.1
    paper_unit_shape_m: float = 0.01
    paper_unit_cam_rot_rad: float = 0.01
    paper_unit_cam_pos_m: float = 0.1
    # product path
    iters: int = 200
    lr: float = 0.03
    expected_noise_px: float = 5.0
    sigma_px_start: float = 40.0
    sigma_px_end: float = 12.0
    w_pose_prior: float = 0.1
    w_limits: float = 100.0
    w_shape: float = 1.0
    accel_sigma_mps2: float = 15.0  # trunk and head joints
    accel_mult_mid: float = 2.0  # elbows, knees
    accel_mult_end: float = 3.0  # wrists, ankles
    w_cam_prior: float = 1.0
    # corrections' knot-to-knot accelerations (the drone's own track is smooth: white GPS/IMU noise is
    # only averaged away over many samples, so the correction must not follow it at short time scales)
    cam_accel_sigma_mps2: float = 0.05
    cam_ang_accel_sigma_radps2: float = 0.005
    cam_smooth_window_s: float = 6.0  # reference track: Savitzky-Golay over this window (clipped to the clip)
    cam_smooth_order: int = 2  # Savitzky-Golay polynomial order of the reference camera track
    cam_knot_s: float = 1.0  # spacing of the camera-correction knots
    # the drones' velocity and angular-velocity samples (when the capture has them): the refined track's
    # displacement / relative rotation between consecutive knots must match their integral; one constant
    # gyro bias per camera is estimated with this prior (RMS 3D, deg/s)
    use_rates: bool = True
    gyro_bias_sigma_degps: float = 0.1
    swap_robust: bool = True
    refine_cameras: bool = True
    #: per-detector joint offsets (:mod:`reconstruction.multiview.offsets`): the product fit compares each detector's
    #: keypoints with joint + R_world_body @ offset (that detector's convention, e.g. shoulders on the body's
    #: surface) instead of the joint centre. "" = none, "builtin" = the committed table learned on the rendered
    #: Anny person (``reconstruction/multiview/data/joint_offsets.toml``), else a TOML path. Detectors that the
    #: table does not name (e.g. the simulator's true projections) get no offset.
    joint_offsets: str = ""
    #: L-BFGS iterations (strong-Wolfe line search) after the Adam steps, at the final robust scale: Adam gets into
    #: the basin, L-BFGS converges in it (0 = Adam only; the monocular body fit uses 1000, see its config)
    polish_iters: int = 0


@dataclasses.dataclass
class FitResult:
    t_ns: np.ndarray  # (T,)
    joints_ned: np.ndarray  # (T, 17, 3)
    root_orient: np.ndarray  # (T, 3) axis-angle body -> world
    pose: np.ndarray  # (T, P, 3)
    transl: np.ndarray  # (T, 3)
    shape: np.ndarray  # (S,)
    cam_index: np.ndarray  # (N,) camera of each refined frame
    cam_t_ns: np.ndarray  # (N,)
    T_world_cam_refined: np.ndarray  # (N, 4, 4)
    T_world_cam_drone: np.ndarray  # (N, 4, 4)
    fit_seconds: float
    method: str
    #: the product fit's objective at its end (per output time, at the final robust scale); comparable between
    #: fits of one capture with one configuration (e.g. from different starts); NaN for the paper path
    energy: float = float("nan")

    def params(self) -> dict:
        return {"root_orient": self.root_orient, "pose": self.pose, "transl": self.transl, "shape": self.shape}


def _gm(e2: torch.Tensor, s: float) -> torch.Tensor:
    """Geman-McClure on squared residuals, scaled to behave like e^2 near 0: s^2 e^2 / (e^2 + s^2)."""
    return s * s * e2 / (e2 + s * s)


def _huber(e2: torch.Tensor, k: float) -> torch.Tensor:
    """Huber on squared normalised residuals: e^2 inside k, linear beyond (a bad sample loses its pull,
    but the track never escapes its GPS/IMU prior altogether, unlike a redescending kernel)."""
    e = torch.sqrt(e2 + 1e-12)
    return torch.where(e <= k, e2, 2 * k * e - k * k)


def _vee2(A: torch.Tensor) -> torch.Tensor:
    """(K, 3) = vee(A - A^T) of matrices A (K, 3, 3): 2 sin(angle) x axis, the rotation vector x 2 for small angles."""
    return torch.stack([A[:, 2, 1] - A[:, 1, 2], A[:, 0, 2] - A[:, 2, 0], A[:, 1, 0] - A[:, 0, 1]], -1)


def _rotvec_to_R(w: torch.Tensor) -> torch.Tensor:
    return sk.axis_angle_to_matrix(w)


def _project(X: torch.Tensor, R_wc: torch.Tensor, p: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Pixels (N, 17, 2) of world points X (N, 17, 3) seen by cameras (R_wc (N, 3, 3), p (N, 3), K (N, 3, 3))."""
    pc = torch.einsum("nji,nkj->nki", R_wc, X - p[:, None])  # R^T (X - p)
    z = pc[..., 2:].clamp(min=0.1)
    xy = pc[..., :2] / z
    return torch.einsum("nij,nkj->nki", K[:, :2, :2], xy) + K[:, None, :2, 2]


def initial_guess(capture: Capture, t_grid_ns: np.ndarray, offsets_body_m: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, tuple]:
    """Robust triangulation at the grid times -> (joints (T, 17, 3), shape (16,), (root_orient, pose, transl) by IK).

    offsets_body_m: (17, 3) the detectors' mean joint offset (:mod:`reconstruction.multiview.offsets`), taken off the
    triangulated points (which lie where the detectors put the joints) before the skeleton is fitted to them."""
    uv, conf, Ts, Ks = interpolate_to_grid(capture, t_grid_ns)
    X = median_in_time(fill_gaps(reject_blunders(triangulate(uv, conf, Ts, Ks))))
    if not np.all(np.isfinite(X)):
        from reconstruction.capture import CaptureError

        raise CaptureError("too few views to triangulate the person (need two cameras seeing each joint sometime)")
    if offsets_body_m is not None:
        X = X - np.einsum("tij,nj->tni", body_frame(X), offsets_body_m)
    return params_from_joints(X)


def params_from_joints(joints_ned: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple]:
    """A start for the fit from 3D joints (T, 17, 3) world NED (finite) -> (the joints, shape (16,),
    (root_orient (T, 3), pose (T, 11, 3), transl (T, 3))) of the skeleton model, by inverse kinematics."""
    X = np.asarray(joints_ned, dtype=float)
    shape = sk.estimate_shape(X)
    R_root, R_loc, transl = sk.inverse_kinematics(X, shape)
    ro = Rotation.from_matrix(R_root).as_rotvec()
    pose = Rotation.from_matrix(R_loc.reshape(-1, 3, 3)).as_rotvec().reshape(len(X), sk.NUM_POSE, 3)
    return X, shape, (ro, pose, transl)


def fit_capture(
    capture: Capture,
    t_grid_ns: np.ndarray,
    cfg: FitConfig | None = None,
    model: BodyModel | None = None,
    prior: PosePrior | None = None,
    progress: bool | Callable[[str, int, int], None] = True,
    init_joints_ned: np.ndarray | None = None,
) -> FitResult:
    """Fit the body to a capture at output times ``t_grid_ns`` (T,) with ``cfg.method``.

    progress: True shows progress bars (stderr), False nothing; a callable is called as
    ``progress(stage, done, total)`` (stages ``"fit"``: optimiser steps / output frames; ``"polish"``: L-BFGS chunks).

    init_joints_ned: (T, 17, 3) world NED, finite: the start at the grid times (e.g. a monocular
    reconstruction, where nothing can be triangulated); default: robust triangulation of the capture.
    """
    cfg = cfg or FitConfig()
    model = model or SkeletonBodyModel()
    prior = prior or load_default_prior()
    fits = {"paper": _fit_paper, "product": _fit_product}
    if cfg.method not in fits:
        raise ValueError(f"unknown method {cfg.method!r}; use 'product' or 'paper'")
    n_threads = torch.get_num_threads()
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    try:
        t_start = time.perf_counter()  # fit_seconds include the start (triangulation)
        t_grid = np.asarray(t_grid_ns, dtype=np.int64)
        if init_joints_ned is not None:
            X0 = np.asarray(init_joints_ned, dtype=float)
            if X0.shape != (len(t_grid), 17, 3) or not np.all(np.isfinite(X0)):
                raise ValueError(f"init_joints_ned must be finite with shape ({len(t_grid)}, 17, 3) (one pose per grid "
                                 f"time), got {X0.shape}{'' if np.all(np.isfinite(X0)) else ' with NaN/inf'}")  # fmt: skip
            start = params_from_joints(X0)
        else:
            # the paper path starts from the first few output times only (like AirCap's online estimate)
            off = _capture_offsets(capture, cfg)
            mean_off = None if off is None or cfg.method != "product" else off.reshape(-1, 17, 3).mean(0)
            start = initial_guess(capture, t_grid if cfg.method == "product" else t_grid[: max(min(len(t_grid), 5), 2)],
                                  mean_off)
        return fits[cfg.method](capture, t_grid, cfg, model, prior, progress, start, t_start)
    finally:
        torch.set_num_threads(n_threads)


def _capture_offsets(capture: Capture, cfg: FitConfig) -> np.ndarray | None:
    """(C, D, 17, 3): each camera's detectors' joint offsets from ``cfg.joint_offsets`` (None: none apply)."""
    table = load_offsets(cfg.joint_offsets)
    if table is None:
        return None
    D = max(c.num_detectors for c in capture.cameras)
    off = np.zeros((capture.num_cameras, D, 17, 3))
    for ci, c in enumerate(capture.cameras):
        off[ci, : c.num_detectors] = table.for_detectors(c.detectors)
    if not np.any(off):
        log.info("joint offsets %r hold none of the capture's detectors (%s): fitting without offsets",
                    cfg.joint_offsets, sorted({d for c in capture.cameras for d in c.detectors}))
        return None
    return off


# ----------------------------------------------------------------------------------------- product
def _fit_product(capture, t_grid, cfg, model, prior, progress, start, t_start) -> FitResult:
    dev = torch.device(cfg.device)
    dt = torch.float32
    model = model.to(dev)
    prior = prior.to(dev)
    _, shape0, (ro0, pose0, tr0) = start
    tracks = [camera_track(c, cfg.cam_smooth_window_s, cfg.cam_smooth_order) for c in capture.cameras]  # once per camera
    obs = gather(capture, t_grid, tracks=tracks)
    T = len(t_grid)
    N = len(obs.t_ns)
    f = lambda a: torch.as_tensor(np.asarray(a), dtype=dt, device=dev)  # noqa: E731
    uv, conf = f(obs.uv), f(obs.conf)  # (N, D, 17, 2), (N, D, 17)
    flip = list(COCO17_FLIP)
    uv_sw, conf_sw = uv[:, :, flip], conf[:, :, flip]
    K = f(obs.K)
    # Cameras: the refined track is the time-smoothed drone track plus a correction that is piecewise
    # linear in time (knots every cam_knot_s per camera: smooth by construction, few unknowns, well
    # conditioned). The GPS/IMU prior compares the refined track with EVERY drone pose sample.
    samp = _pose_samples(capture, obs, t_grid, tracks)
    R_raw_s, p_raw_s = f(samp["T_est"][:, :3, :3]), f(samp["T_est"][:, :3, 3])
    R_sm_s, p_sm_s = f(samp["T_smooth"][:, :3, :3]), f(samp["T_smooth"][:, :3, 3])
    R_sm_f, p_sm_f = f(obs.T_smooth[:, :3, :3]), f(obs.T_smooth[:, :3, 3])
    knots = _knots(samp, obs, cfg.cam_knot_s)
    kf0, wf = torch.as_tensor(knots["f_i0"], device=dev), f(knots["f_w"])[:, None]
    ks0, ws = torch.as_tensor(knots["s_i0"], device=dev), f(knots["s_w"])[:, None]
    NK = knots["n"]
    k0 = torch.as_tensor(obs.k, device=dev)
    a = f(obs.alpha)[:, None, None]
    ps, rs = f(np.maximum(samp["pos_sigma_m"], 1e-3)), f(np.maximum(samp["rot_sigma_rad"], 1e-4))
    dt_knot = cfg.cam_knot_s
    fps = (T - 1) / ((t_grid[-1] - t_grid[0]) * 1e-9)
    # extremities accelerate more: elbows/knees x2, wrists/ankles x3 the trunk's sigma
    mult = np.ones(17)
    mult[[7, 8, 13, 14]] = cfg.accel_mult_mid
    mult[[9, 10, 15, 16]] = cfg.accel_mult_end
    acc_sigma = f(cfg.accel_sigma_mps2 * mult)[None, :, None]

    ro = f(ro0).requires_grad_()
    pose = f(pose0).requires_grad_()
    tr = f(tr0).requires_grad_()
    shape = f(shape0).requires_grad_()
    dw = torch.zeros(NK, 3, dtype=dt, device=dev, requires_grad=True)
    dp = torch.zeros(NK, 3, dtype=dt, device=dev, requires_grad=True)
    # consecutive frames of the same camera (for camera smoothness)
    knot_runs = [(k0_, k1_) for k0_, k1_ in knots["cam_ranges"] if k1_ - k0_ >= 3]
    off_c = _capture_offsets(capture, cfg)
    off_f = None if off_c is None else f(off_c[obs.cam])  # (N, D, 17, 3) each frame's detectors' offsets
    noise2 = cfg.expected_noise_px**2
    rc = _rate_constraints(capture, samp, knots) if (cfg.use_rates and cfg.refine_cameras) else {}
    rv, ro_ = rc.get("vel"), rc.get("omega")
    if rv is not None:
        rv = {k: (torch.as_tensor(v, device=dev) if k.endswith("i0") else f(v)[:, None] if k.endswith("_w") else f(v)) for k, v in rv.items()}
    gyro_bias = torch.zeros(capture.num_cameras, 3, dtype=dt, device=dev, requires_grad=True)
    if ro_ is not None:
        ro_ = {k: (torch.as_tensor(v, device=dev) if k.endswith("i0") or k == "cam" else f(v)[:, None] if k.endswith("_w") else f(v)) for k, v in ro_.items()}
    bias_sig = np.radians(cfg.gyro_bias_sigma_degps) / np.sqrt(3.0)

    def knot_interp(c: torch.Tensor, i0: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """Piecewise-linear corrections c (NK, 3) at points with knot index i0 (K,) and weight w (K, 1)."""
        return (1 - w) * c[i0] + w * c[i0 + 1]

    def cam_poses():
        """Refined poses at the frames (N) and at the drone pose samples (M)."""
        dwf, dpf = knot_interp(dw, kf0, wf), knot_interp(dp, kf0, wf)
        dws, dps = knot_interp(dw, ks0, ws), knot_interp(dp, ks0, ws)
        return _rotvec_to_R(dwf) @ R_sm_f, p_sm_f + dpf, _rotvec_to_R(dws) @ R_sm_s, p_sm_s + dps

    def cam_energy(Rs: torch.Tensor, pss: torch.Tensor) -> torch.Tensor:
        """The cameras' own terms (no images): GPS/IMU prior, correction smoothness, rates."""
        # GPS/IMU prior: refined track vs every drone pose sample (robust, the drones' own sigmas)
        # the capture's sigmas are RMS 3D errors (sqrt of the covariance trace): per axis sigma^2 / 3
        e_p = 3.0 * ((pss - p_raw_s) ** 2).sum(-1) / ps**2
        dR = Rs @ R_raw_s.transpose(-1, -2)
        e_r = 3.0 * (_vee2(dR) ** 2).sum(-1) / 4 / rs**2
        E_cam = cfg.w_cam_prior * 0.5 * (_huber(e_p, 3.0).sum() + _huber(e_r, 3.0).sum())
        # motion smoothness of the corrections (second differences at the knots)
        for k0_, k1_ in knot_runs:
            ap = (dp[k0_ + 2 : k1_] - 2 * dp[k0_ + 1 : k1_ - 1] + dp[k0_ : k1_ - 2]) / dt_knot**2
            ar = (dw[k0_ + 2 : k1_] - 2 * dw[k0_ + 1 : k1_ - 1] + dw[k0_ : k1_ - 2]) / dt_knot**2
            E_cam = E_cam + 0.5 * (ap**2).sum() / cfg.cam_accel_sigma_mps2**2 + 0.5 * (ar**2).sum() / cfg.cam_ang_accel_sigma_radps2**2
        if rv is not None:  # displacement between knots = integrated velocity
            d = knot_interp(dp, rv["b_i0"], rv["b_w"]) - knot_interp(dp, rv["a_i0"], rv["a_w"]) - rv["m"]
            E_cam = E_cam + 0.5 * ((d / rv["sigma"][:, None]) ** 2).sum()
        if ro_ is not None:  # relative rotation between knots = integrated angular velocity (minus gyro bias)
            Ra = _rotvec_to_R(knot_interp(dw, ro_["a_i0"], ro_["a_w"])) @ ro_["Ra"]
            Rb = _rotvec_to_R(knot_interp(dw, ro_["b_i0"], ro_["b_w"])) @ ro_["Rb"]
            A = ro_["M"].transpose(-1, -2) @ Ra.transpose(-1, -2) @ Rb
            d = 0.5 * _vee2(A)
            d = d + ro_["span"][:, None] * gyro_bias[ro_["cam"]]
            E_cam = E_cam + 0.5 * ((d / ro_["sigma"][:, None]) ** 2).sum() + 0.5 * (gyro_bias**2).sum() / bias_sig**2
        return E_cam

    def energy(sig: float) -> torch.Tensor:
        X = model(ro, pose, tr, shape)  # (T, 17, 3)
        Xo = (1 - a) * X[k0] + a * X[k0 + 1]  # (N, 17, 3) at the frames' capture times
        R, p, Rs, pss = cam_poses()
        if off_f is None:
            pix = _project(Xo, R, p, K)[:, None]  # (N, 1, 17, 2)
        else:  # each detector's points: joint + R_world_body @ its offset
            Xd = Xo[:, None] + torch.einsum("nij,ndkj->ndki", body_frame_torch(Xo), off_f)  # (N, D, 17, 3)
            pix = _project(Xd.reshape(N, -1, 3), R, p, K).reshape(uv.shape)  # (N, D, 17, 2)
        e2 = ((pix - uv) ** 2).sum(-1)  # (N, D, 17)
        cost = (conf * _gm(e2, sig)).sum(-1)
        if cfg.swap_robust:
            e2s = ((pix - uv_sw) ** 2).sum(-1)
            cost = torch.minimum(cost, (conf_sw * _gm(e2s, sig)).sum(-1))
        E_data = cost.sum() / noise2 * 0.5
        E_prior = cfg.w_pose_prior * prior.energy(pose).sum() + cfg.w_limits * prior.limit_penalty(pose).sum()
        E_shape = cfg.w_shape * model.shape_energy(shape)
        Xs = model(ro, pose, tr, shape.detach())  # smoothness must not shrink the skeleton
        acc = (Xs[2:] - 2 * Xs[1:-1] + Xs[:-2]) * fps * fps
        E_smooth = 0.5 * ((acc / acc_sigma) ** 2).sum()
        E_cam = cam_energy(Rs, pss) if cfg.refine_cameras else torch.zeros((), device=dev)
        return (E_data + E_prior + E_shape + E_smooth + E_cam) / T

    groups = [{"params": [ro, pose], "lr": cfg.lr}, {"params": [tr], "lr": cfg.lr * 0.5}, {"params": [shape], "lr": cfg.lr * 0.25}]
    if cfg.refine_cameras:
        groups += [{"params": [dw], "lr": cfg.lr * 0.25}, {"params": [dp], "lr": cfg.lr}]
    if ro_ is not None:
        groups += [{"params": [gyro_bias], "lr": cfg.lr * 0.01}]
    opt = Adam(groups)  # torch.optim.Adam's numbers without its seconds-long torch._dynamo import (reconstruction.optim)
    sched = OneCycle(opt, total_steps=cfg.iters, pct_start=0.15, max_lr=[g["lr"] for g in groups])
    bar = tqdm(range(cfg.iters), desc="fit (product)", disable=progress is not True, leave=False)
    for i in bar:
        _report(progress, "fit", i, cfg.iters)
        # robust scale annealed from sigma_px_start to sigma_px_end over the first 60 % of the steps
        sig = cfg.sigma_px_end + (cfg.sigma_px_start - cfg.sigma_px_end) * max(0.0, 1 - i / (0.6 * cfg.iters))
        opt.zero_grad()
        E = energy(sig)
        E.backward()
        opt.step()
        sched.step()
        if progress is True and i % 25 == 0:
            bar.set_postfix(E=f"{E.item():.2f}")
    _report(progress, "fit", cfg.iters, cfg.iters)
    if cfg.polish_iters > 0:
        lbfgs_polish(lambda: energy(cfg.sigma_px_end), [q for g in groups for q in g["params"]], cfg.polish_iters, progress)
    with torch.no_grad():
        E_final = float(energy(cfg.sigma_px_end))
        X = model(ro.double(), pose.double(), tr.double(), shape.double())  # float64: exports match exactly
        R, p, _, _ = cam_poses()
    T_ref = np.tile(np.eye(4), (N, 1, 1))
    T_ref[:, :3, :3] = R.double().cpu().numpy()
    T_ref[:, :3, 3] = p.double().cpu().numpy()
    return FitResult(
        t_ns=t_grid, joints_ned=X.double().cpu().numpy(), root_orient=ro.detach().double().cpu().numpy(),
        pose=pose.detach().double().cpu().numpy(), transl=tr.detach().double().cpu().numpy(),
        shape=shape.detach().double().cpu().numpy(), cam_index=obs.cam, cam_t_ns=obs.t_ns,
        T_world_cam_refined=T_ref, T_world_cam_drone=obs.T_est, fit_seconds=time.perf_counter() - t_start, method="product",
        energy=E_final,
    )  # fmt: skip


def _report(progress, stage: str, done: int, total: int) -> None:
    if callable(progress):
        progress(stage, done, total)


def lbfgs_polish(energy_fn, params: list[torch.Tensor], iters: int, progress: bool | Callable = False, chunk: int = 50) -> float:
    """Minimise ``energy_fn()`` (a scalar tensor of ``params``) with L-BFGS from the parameters' current values.

    ``iters`` iterations in chunks of ``chunk`` (one progress step each; the history carries over). Stops early when
    a chunk no longer lowers the energy; a chunk that makes it non-finite or higher is undone. Returns the final
    energy. Used after Adam, which finds the basin but converges slowly in it."""
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=chunk, history_size=20, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-9, tolerance_change=1e-12)

    def closure():
        opt.zero_grad(set_to_none=True)
        E = energy_fn()
        E.backward()
        return E

    with torch.no_grad():
        E_prev = float(energy_fn())
    n_chunks = -(-int(iters) // chunk)
    bar = tqdm(range(n_chunks), desc="fit (L-BFGS)", disable=progress is not True, leave=False)
    for k in bar:
        _report(progress, "polish", k, n_chunks)
        saved = [q.detach().clone() for q in params]
        opt.step(closure)
        with torch.no_grad():
            E = float(energy_fn())
        if not np.isfinite(E) or E > E_prev:
            with torch.no_grad():
                for q, q0 in zip(params, saved):
                    q.copy_(q0)
            break
        done = E > E_prev - 1e-6 * abs(E_prev)
        E_prev = E
        if progress is True:
            bar.set_postfix(E=f"{E:.3f}")
        if done:
            break
    _report(progress, "polish", n_chunks, n_chunks)
    return E_prev


def _knots(samp: dict, obs, spacing_s: float) -> dict:
    """Per camera knot times covering its samples and frames; interpolation index/weight of every frame
    (``f_i0``, ``f_w``) and sample (``s_i0``, ``s_w``) into the concatenated knots."""
    f_i0 = np.zeros(len(obs.t_ns), dtype=np.int64)
    f_w = np.zeros(len(obs.t_ns))
    s_i0 = np.zeros(len(samp["t_ns"]), dtype=np.int64)
    s_w = np.zeros(len(samp["t_ns"]))
    ranges, times, n0 = [], [], 0
    step = int(spacing_s * 1e9)
    for ci, (a0, a1) in enumerate(samp["cam_ranges"]):
        ts = samp["t_ns"][a0:a1]
        sl = obs.cam_slices[ci]
        tf = obs.t_ns[sl]
        lo = min(ts.min(), tf.min()) if len(tf) else ts.min()
        hi = max(ts.max(), tf.max()) if len(tf) else ts.max()
        nk = max(2, int(np.ceil((hi - lo) / step)) + 1)
        kt = lo + np.arange(nk, dtype=np.int64) * step
        for t, i0, w, idx in ((tf, f_i0, f_w, sl), (ts, s_i0, s_w, slice(a0, a1))):
            k = np.clip(np.searchsorted(kt, t, side="right") - 1, 0, nk - 2)
            i0[idx] = n0 + k
            w[idx] = np.clip((t - kt[k]) / step, 0.0, 1.0)
        ranges.append((n0, n0 + nk))
        times.append(kt)
        n0 += nk
    return {"n": n0, "f_i0": f_i0, "f_w": f_w, "s_i0": s_i0, "s_w": s_w, "cam_ranges": ranges, "times": times}


def _pose_samples(capture: Capture, obs, t_grid: np.ndarray, tracks: list[np.ndarray]) -> dict:
    """The drones' pose samples covering the frames: times (M,), T_est/T_smooth (M, 4, 4) (``tracks``: each
    camera's reference track at all its pose samples, :func:`camera_track`), sigmas (M,), per camera index
    ranges, and for every frame n its interval j0[n] (into the M samples) and weight beta[n]."""
    ts, Te, Tsm, ps, rs, ranges, src = [], [], [], [], [], [], []
    j0 = np.zeros(len(obs.t_ns), dtype=np.int64)
    beta = np.zeros(len(obs.t_ns))
    m0 = 0
    for ci, cam in enumerate(capture.cameras):
        sl = obs.cam_slices[ci]
        tf = obs.t_ns[sl]
        lo = min(int(t_grid[0]), int(tf.min()) if len(tf) else int(t_grid[0]))
        hi = max(int(t_grid[-1]), int(tf.max()) if len(tf) else int(t_grid[-1]))
        i_lo = max(int(np.searchsorted(cam.t_pose_ns, lo, side="right")) - 1, 0)
        i_hi = min(int(np.searchsorted(cam.t_pose_ns, hi, side="left")) + 1, len(cam.t_pose_ns))
        idx = np.arange(i_lo, i_hi)
        t_s = cam.t_pose_ns[idx]
        T_s = cam.T_world_cam[idx]
        if len(t_s) < 2:  # a single pose: use it at both ends
            t_s = np.array([lo - 1, hi + 1], dtype=np.int64)
            T_s = np.stack([cam.T_world_cam[idx[0] if len(idx) else 0]] * 2)
        T_sm = tracks[ci][idx] if len(idx) == len(t_s) else T_s
        k = np.clip(np.searchsorted(t_s, tf, side="right") - 1, 0, len(t_s) - 2)
        j0[sl] = m0 + k
        beta[sl] = np.clip((tf - t_s[k]) / np.maximum(t_s[k + 1] - t_s[k], 1), 0.0, 1.0)
        p_sig, r_sig = cam.sigma_at(t_s)
        ts.append(t_s), Te.append(T_s), Tsm.append(T_sm), ps.append(p_sig), rs.append(np.radians(r_sig))
        src.append(idx if len(idx) == len(t_s) else None)  # indices into the camera's own pose samples
        ranges.append((m0, m0 + len(t_s)))
        m0 += len(t_s)
    c = np.concatenate
    return {"t_ns": c(ts), "T_est": c(Te), "T_smooth": c(Tsm), "pos_sigma_m": c(ps), "rot_sigma_rad": c(rs),
            "cam_ranges": ranges, "j0": j0, "beta": beta, "src": src}  # fmt: skip


def _cumulative_rotations(steps: Rotation) -> Rotation:
    """G (n + 1,) with G[0] = identity and G[k] = steps[0] * ... * steps[k - 1] (the rotation integrated over
    the first k steps), as a prefix scan in log2(n) vectorised compositions instead of n single ones."""
    q = np.concatenate([[[0.0, 0.0, 0.0, 1.0]], steps.as_quat()])  # scipy order (x, y, z, w)
    d = 1
    while d < len(q):
        q = np.concatenate([q[:d], (Rotation.from_quat(q[:-d]) * Rotation.from_quat(q[d:])).as_quat()])
        d *= 2
    return Rotation.from_quat(q)


def _rate_constraints(capture: Capture, samp: dict, knots: dict) -> dict:
    """Velocity / angular-velocity constraints between consecutive knots of every camera that has them.

    For each camera, the knot times clipped to its pose samples give intervals [a, b]; per interval:
    knot interpolation (index, weight) of a and b, and for velocity ``m`` (K, 3) = integral of the
    measured velocity minus the reference track's displacement (the corrections' displacement must
    equal it) with its per-axis sigma (white noise integrated: sigma_axis^2 * sum(dt^2)); for angular
    velocity the reference rotations at a and b ``Ra``/``Rb`` (K, 3, 3), the integrated relative
    rotation ``M`` (K, 3, 3) (R(b) = R(a) M), its per-axis sigma, the interval length ``span`` (s) and
    the camera ``cam`` (for the gyro bias). Returns {"vel": ..., "omega": ...} (absent: no such data).
    """
    from reconstruction.capture import interpolate_poses

    out: dict[str, dict[str, list]] = {}
    for ci, cam in enumerate(capture.cameras):
        a0, a1 = samp["cam_ranges"][ci]
        idx = samp["src"][ci]
        if idx is None or a1 - a0 < 3 or not (cam.has_velocity or cam.has_angular_velocity):
            continue
        t_s = samp["t_ns"][a0:a1]
        T_sm = samp["T_smooth"][a0:a1]
        kt = knots["times"][ci]
        k_lo = knots["cam_ranges"][ci][0]
        tau = np.unique(np.clip(kt, t_s[0], t_s[-1]))
        if len(tau) < 2:
            continue
        k = np.clip(np.searchsorted(kt, tau, side="right") - 1, 0, len(kt) - 2)
        i0, w = k_lo + k, np.clip((tau - kt[k]) / (kt[1] - kt[0]), 0.0, 1.0)
        ts = (t_s - t_s[0]) * 1e-9
        tq = (tau - t_s[0]) * 1e-9
        dts = np.diff(ts)
        span = np.diff(tq)
        # per interval: sum of squared sample steps inside it (integrated white noise)
        cum_dt2 = np.concatenate([[0.0], np.cumsum(dts**2)])
        sum_dt2 = np.maximum(np.diff(np.interp(tq, ts, cum_dt2)), 1e-12)
        base = {"a_i0": i0[:-1], "a_w": w[:-1], "b_i0": i0[1:], "b_w": w[1:]}
        if cam.has_velocity:
            v = cam.vel_world_mps[idx]
            cum = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (v[1:] + v[:-1]) * dts[:, None], axis=0)])
            C = np.stack([np.interp(tq, ts, cum[:, j]) for j in range(3)], -1)
            P_ref = np.stack([np.interp(tq, ts, T_sm[:, j, 3]) for j in range(3)], -1)
            sig_axis = np.interp(tq[:-1], ts, cam.vel_sigma_mps[idx]) / np.sqrt(3.0)
            e = {**base, "m": np.diff(C, axis=0) - np.diff(P_ref, axis=0), "sigma": np.sqrt(sig_axis**2 * sum_dt2 + 1e-6)}
            for key, val in e.items():
                out.setdefault("vel", {}).setdefault(key, []).append(val)
        if cam.has_angular_velocity:
            om = cam.omega_cam_radps[idx]
            G = _cumulative_rotations(Rotation.from_rotvec(om[:-1] * dts[:, None]))
            kk = np.clip(np.searchsorted(ts, tq, side="right") - 1, 0, len(ts) - 2)
            Gq = G[kk] * Rotation.from_rotvec(om[kk] * (tq - ts[kk])[:, None])
            M = (Gq[:-1].inv() * Gq[1:]).as_matrix()
            R_ref = interpolate_poses(t_s, T_sm, tau)[:, :3, :3]
            sig_axis = np.interp(tq[:-1], ts, cam.omega_sigma_radps[idx]) / np.sqrt(3.0)
            e = {**base, "Ra": R_ref[:-1], "Rb": R_ref[1:], "M": M, "span": span,
                 "sigma": np.sqrt(sig_axis**2 * sum_dt2 + 1e-10), "cam": np.full(len(span), ci)}  # fmt: skip
            for key, val in e.items():
                out.setdefault("omega", {}).setdefault(key, []).append(val)
    return {name: {key: np.concatenate(vals) for key, vals in d.items()} for name, d in out.items()}


# ------------------------------------------------------------------------------------------- paper
def _fit_paper(capture, t_grid, cfg, model, prior, progress, start, t_start) -> FitResult:
    dev = torch.device(cfg.device)
    dt = torch.float32
    model = model.to(dev)
    prior = prior.to(dev)
    # first frame's start: the start's first output time (robust triangulation, like AirCap's online estimate)
    _, shape0, (ro0, pose0, tr0) = start
    f = lambda a: torch.as_tensor(np.asarray(a), dtype=dt, device=dev)  # noqa: E731
    C = capture.num_cameras
    D = max(c.num_detectors for c in capture.cameras)
    ro = f(ro0[:1]).clone()
    pose = f(pose0[:1]).clone()
    tr = f(tr0[:1]).clone()
    shape = f(shape0[None]).clone()
    s1, s2 = cfg.sigma1_px, cfg.sigma2
    out_X, out_ro, out_pose, out_tr, out_shape = [], [], [], [], []
    cam_idx, cam_t, T_ref, T_dr = [], [], [], []
    it = tqdm(range(len(t_grid)), desc="fit (paper)", disable=progress is not True, leave=False)
    for ti in it:
        _report(progress, "fit", ti, len(t_grid))
        t = t_grid[ti]
        uv = np.zeros((C, D, 17, 2))
        cf = np.zeros((C, D, 17))
        Rt, pt, Kt = np.zeros((C, 3, 3)), np.zeros((C, 3)), np.zeros((C, 3, 3))
        for ci, c in enumerate(capture.cameras):
            fi = int(np.argmin(np.abs(c.t_frame_ns - t)))  # nearest frame in time
            uv[ci, : c.num_detectors] = c.keypoints_px[fi]
            cf[ci, : c.num_detectors] = c.confidence[fi]
            Tc = c.pose_at(c.t_frame_ns[fi])[0]
            Rt[ci], pt[ci], Kt[ci] = Tc[:3, :3], Tc[:3, 3], c.K_at(c.t_frame_ns[fi])[0]
            cam_idx.append(ci)
            cam_t.append(int(c.t_frame_ns[fi]))
            T_dr.append(Tc)
        r_tilde = f(Rotation.from_matrix(Rt).as_rotvec())
        p_tilde = f(pt)
        uv_t, cf_t, K_t = f(uv), f(cf), f(Kt)
        u = (cfg.paper_unit_rot_rad, cfg.paper_unit_rot_rad, cfg.paper_unit_transl_m, cfg.paper_unit_shape_m)
        v_ro, v_pose, v_tr, v_sh = (torch.clone(x / k).requires_grad_() for x, k in zip((ro, pose, tr, shape), u))
        v_r = (r_tilde / cfg.paper_unit_cam_rot_rad).clone().requires_grad_()
        v_p = (p_tilde / cfg.paper_unit_cam_pos_m).clone().requires_grad_()
        first = ti == 0
        n_it, lr = (cfg.paper_first_iters, cfg.paper_first_lr) if first else (cfg.paper_iters, cfg.paper_lr)
        opt = Adam([v_ro, v_pose, v_tr, v_sh, v_r, v_p], lr=lr)
        for _ in range(n_it):
            opt.zero_grad()
            ro, pose, tr, shape = v_ro * u[0], v_pose * u[1], v_tr * u[2], v_sh * u[3]
            r, p = v_r * cfg.paper_unit_cam_rot_rad, v_p * cfg.paper_unit_cam_pos_m
            X = model(ro, pose, tr, shape[0])  # (1, 17, 3)
            pix = _project(X.expand(C, -1, -1), _rotvec_to_R(r), p, K_t)  # (C, 17, 2)
            e2 = ((pix[:, None] - uv_t) ** 2).sum(-1)
            E2d = (cf_t * e2 / (e2 + s1 * s1)).sum()
            er2 = (torch.rad2deg(r - r_tilde) ** 2).sum(-1)  # degrees
            ep2 = ((100.0 * (p - p_tilde)) ** 2).sum(-1)  # centimetres
            Erp = (er2 / (er2 + s2 * s2) + ep2 / (ep2 + s2 * s2)).sum()
            E = E2d + cfg.paper_w_cam * Erp + cfg.paper_w_pose * prior.energy(pose).sum() + cfg.paper_w_shape * model.shape_energy(shape[0])
            E.backward()
            opt.step()
        with torch.no_grad():
            ro, pose, tr, shape = v_ro * u[0], v_pose * u[1], v_tr * u[2], v_sh * u[3]
            r, p = v_r * cfg.paper_unit_cam_rot_rad, v_p * cfg.paper_unit_cam_pos_m
            out_X.append(model(ro.double(), pose.double(), tr.double(), shape[0].double())[0].cpu().numpy())
            out_ro.append(ro[0].double().cpu().numpy())
            out_pose.append(pose[0].double().cpu().numpy())
            out_tr.append(tr[0].double().cpu().numpy())
            out_shape.append(shape[0].double().cpu().numpy())
            Rr = _rotvec_to_R(r).double().cpu().numpy()
            for ci in range(C):
                Tm = np.eye(4)
                Tm[:3, :3], Tm[:3, 3] = Rr[ci], p[ci].double().cpu().numpy()
                T_ref.append(Tm)
        ro, pose, tr, shape = (v.detach() for v in (ro, pose, tr, shape))
    _report(progress, "fit", len(t_grid), len(t_grid))
    return FitResult(
        t_ns=t_grid, joints_ned=np.array(out_X), root_orient=np.array(out_ro), pose=np.array(out_pose),
        transl=np.array(out_tr), shape=np.median(np.array(out_shape), 0), cam_index=np.array(cam_idx),
        cam_t_ns=np.array(cam_t, dtype=np.int64), T_world_cam_refined=np.array(T_ref), T_world_cam_drone=np.array(T_dr),
        fit_seconds=time.perf_counter() - t_start, method="paper",
    )  # fmt: skip
