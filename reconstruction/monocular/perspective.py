"""Perspective bundle adjustment with the drone's known camera poses (beyond DroCap; the "product" variant).

The paper's BA (:mod:`reconstruction.monocular.ba`) models an orthographic camera whose rotation R_t is
unknown. A drone knows (up to its GPS/IMU error) where its camera is and where it points: ``T_world_cam``
per frame and the intrinsics ``K``. :func:`perspective_bundle_adjust` therefore optimises the joints
directly in the world frame (NED metres).

**Scale gauge.** Scaling frame t's joints about its camera centre p_t by one common factor e^s changes no
projection: with one camera the image fixes the body only up to that factor. It is made explicit: Y_t (root
c_t (T, 3) + centred pose P_t (T, J, 3), bone lengths b (nL,) whose RMS over the 12 limb/torso bones is fixed
to ``body_bone_rms_m``) is the body at the reference size, and the world joints are
X_t = p_t + e^s (Y_t - p_t). The objective is::

    F =   sum_tj w_tj rho_GM(||pi(K, T_world_cam_t, Y_tj) - W_tj|| / sigma)      robust reprojection (= of X)
        + (1 / s_b^2)   sum_tl (||Y_ta - Y_tb|| - b_l)^2                          articulation (metric rank-1)
        + s^2 / s_s^2 + sum_l (log b_l - log b_ref_l)^2 / s_p^2                   size and proportions priors
        + (1 / s_P^2)   sum_t ||acc(P)_t||^2  + (1 / s_c^2) sum_t ||acc(c)_t||^2  pose and root smoothness (of Y)
        + (1 / s_X^2)   sum_t (h_t / tau) ||acc(G X_root)_t||^2                   parallax: the low-passed WORLD
                                                                                  root path moves like a person
        + alpha sqrt(T) sum_i sqrt(lambda_i(P#^T P#) + T eps^2)                    smoothed nuclear norm of P#
        + (1 / s_r^2)   sum_t ||v_t||^2                                            camera corrections
        + cheirality: every joint at least ``min_depth_m`` in front of its camera

with acc() the second derivative on the true (uneven) frame times, G a Gaussian low-pass of time scale
``parallax_tau_s``, b_ref the adult bone lengths :data:`ADULT_BONES_M` (posture-free, unlike the RMS joint
radius), the camera rotation of frame t exp([v_t]x) R_cw_t (a small per-frame correction v_t absorbs the
drone's attitude error and, to first order, its position error), rho_GM(r) = r^2 / (1 + r^2) (annealed from
a wide ``sigma`` down to ``robust_scale_px``), w = confidence x inlier, P# the centred poses as columns. The
metric scale e^s is set by the size prior and by the orbit's parallax: a wrong e^s adds (e^s - 1) times the
camera's own orbit to the world root path. Shape priors act on Y, so that shrinking the body towards the
cameras is not rewarded; the per-frame root smoothness acts on Y too (the drone's white position noise and
the image-size noise of the depth would otherwise bias e^s), the parallax term on the low-passed world path.
A redundant coordinate moves all roots of Y along their camera rays by one factor (at fixed body size: the
image size changes): the depth, badly conditioned in per-frame coordinates, converges in a few iterations.

Solved with L-BFGS (strong Wolfe line search) in torch (CPU, float64), vectorised over frames.
:func:`orthographic_to_world` places the paper BA's result in the world to start from (depth from the bones'
image size, robust over time: :func:`robust_depth_track`).

History: the earlier version fixed the pose's RMS joint radius (0.55 m, posture-dependent) and had only the
redundant scale of the roots about the cameras. On a real single-drone flight (small, noisy person; see
``tests/recon_monocular/test_monocular_world_placement.py``) its start came from near-zero orthographic poses
with astronomically large depths, every reprojection residual saturated, and the roots slid onto the camera
centres (9.2 m from the truth).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from reconstruction.monocular.linalg import complete_rotation
from skycap.errors import SkycapError

log = logging.getLogger(__name__)

__all__ = ["PerspectiveConfig", "PerspectiveResult", "perspective_bundle_adjust", "orthographic_to_world", "bone_lengths",
           "robust_depth_track", "body_limb_index", "ADULT_BONE_RMS_M", "ADULT_BONES_M"]


#: Adult bone lengths (metres) of the COCO-17 limb and torso bones: the perspective BA's prior on the body's
#: proportions and size. Medians over the 35 CMU clips of ``../shared/data/mocap/cmu`` (subjects 001-005,
#: retargeted to one CC_Base skeleton, so all clips share them; the simulator's body too, within 1 cm): a
#: typical adult of about 1.8 m. Real people differ by a few per cent in proportions and ~10 % in size, hence
#: the soft priors ``bone_prior_sigma`` and ``size_prior_sigma``.
ADULT_BONES_M: dict[tuple[int, int], float] = {
    (5, 7): 0.252, (7, 9): 0.257, (6, 8): 0.252, (8, 10): 0.257,  # upper arms, forearms
    (11, 13): 0.477, (13, 15): 0.498, (12, 14): 0.477, (14, 16): 0.498,  # thighs, shins
    (5, 6): 0.367, (11, 12): 0.194, (5, 11): 0.497, (6, 12): 0.490,  # shoulders, hips, flanks
}  # fmt: skip
#: RMS of :data:`ADULT_BONES_M` (0.394 m; the RMS joint radius, by contrast, depends on the posture: 0.51-0.60 m
#: over the same clips, less when crouching).
ADULT_BONE_RMS_M = float(np.sqrt(np.mean(np.square(list(ADULT_BONES_M.values())))))


@dataclasses.dataclass
class PerspectiveConfig:
    robust_scale_px: float = 8.0  # Geman-McClure scale sigma (final)
    robust_scale_start_px: float = 40.0  # first stage's sigma (annealing)
    bone_sigma_m: float = 0.01  # articulation: allowed bone-length variation
    pose_acc_sigma_mps2: float = 30.0  # pose smoothness: typical joint acceleration relative to the root
    root_acc_sigma_mps2: float = 10.0  # root smoothness (the body centre moves smoothly; also absorbs camera noise)
    alpha: float = 0.1  # smoothed nuclear norm weight (times sqrt(T)), metres
    body_rms_radius_m: float = 0.55  # RMS joint radius assumed when placing the orthographic start (init only)
    body_bone_rms_m: float = ADULT_BONE_RMS_M  # size prior: RMS of the limb/torso bone lengths (metres)
    size_prior_sigma: float = 0.1  # std of the log body size about body_bone_rms_m (adults: about +-10 %)
    bone_prior_sigma: float = 0.08  # std of each log bone length about ADULT_BONES_M (proportions; 0 = no prior)
    #: the person's own bone lengths (metres) when known (e.g. measured), in the order of ADULT_BONES_M's keys;
    #: empty = the adult reference. Only their proportions are used (the size is body_bone_rms_m's).
    bone_prior_m: tuple[float, ...] = ()
    min_depth_m: float = 0.5  # cheirality: joints closer to (or behind) the camera are penalised
    camera_sigma_deg: float = 3.0  # prior std of the per-frame camera rotation corrections (0 = trust the poses)
    parallax_tau_s: float = 1.0  # time scale of the parallax term (Gaussian low-pass of the world root path)
    parallax_acc_sigma_mps2: float = 0.4  # per axis, of that low-passed root (CMU: 3D RMS 0.03-0.4 m/s^2; demo person 0.2)
    depth_gain: float = 1.0  # preconditioning of the joints' depth (camera z) coordinates
    nuclear_eps_m: float = 0.01  # smoothing of the nuclear norm (per-frame RMS metres)
    iters_per_stage: int = 60
    stages: int = 3  # sigma goes geometrically from robust_scale_start_px to robust_scale_px


@dataclasses.dataclass
class PerspectiveResult:
    X: np.ndarray  # (T, J, 3) world joints, NED metres
    bones_m: np.ndarray  # (nL,) bone lengths
    objective: np.ndarray  # (n,) F at the start and after each stage (each stage at its own sigma)
    objective_final_sigma: tuple[float, float]  # F at the final sigma: (start, end)
    iterations: int
    body_scale: float = 1.0  # e^s: body size relative to body_bone_rms_m (the estimated metric scale)


def body_limb_index(limbs) -> np.ndarray:
    """Indices of the limbs between body joints (COCO-17 index >= 5: torso and limbs, not the face)."""
    return np.array([i for i, l in enumerate(limbs) if min(l) >= 5], dtype=int)


def bone_lengths(X: np.ndarray, limbs) -> np.ndarray:
    """(T, nL) bone lengths of joints X (T, J, 3)."""
    a = np.array([l[0] for l in limbs])
    b = np.array([l[1] for l in limbs])
    return np.linalg.norm(X[:, a] - X[:, b], axis=-1)


def robust_depth_track(size_px: np.ndarray, size_m: float, focal_px: np.ndarray, n_obs: np.ndarray, min_obs: int = 6,
                       window: int = 25) -> np.ndarray:
    """Depth (T,) of the body centre, metres, from its image size: ``f * size_m / size_px`` per frame, robustly.

    Frames with fewer than ``min_obs`` observed keypoints, a degenerate size (a collapsed pose) or a depth more
    than a factor 3 from the median are not trusted; their log-depth is interpolated in time from the
    trusted frames, and the result is median-filtered over ``window`` frames (one body, smooth motion). A
    single degenerate frame could otherwise put the body kilometres away. Shapes: size_px, focal_px, n_obs (T,).
    """
    from scipy.ndimage import median_filter

    T = len(size_px)
    with np.errstate(divide="ignore", invalid="ignore"):
        logd = np.log(focal_px * size_m / size_px)
    ok = np.isfinite(logd) & (n_obs >= min_obs) & (size_px > 1e-6)
    if not ok.any():
        ok = np.isfinite(logd)
    if not ok.any():
        raise SkycapError("cannot place the body: no frame has a usable pose size; check the 2D keypoints")
    med = np.median(logd[ok])
    ok &= np.abs(logd - med) < np.log(3.0)
    idx = np.arange(T)
    logd = np.interp(idx, idx[ok], logd[ok])
    return np.exp(median_filter(logd, size=min(T, window), mode="nearest"))


def orthographic_to_world(S_px, R, W_px, weights, T_world_cam, K, body_rms_radius_m, frame: str = "canonical",
                          limbs=None, bone_rms_m: float | None = None) -> np.ndarray:
    """A BA's orthographic poses placed in the world: (T, J, 3) NED metres.

    Camera coordinates of pose t are Rbar_t S_t (Rbar = R completed to a rotation; with ``frame="world"``
    S_t is already in world axes, the extended BA), scaled to metres with the assumed body size: its RMS
    joint radius ``body_rms_radius_m`` or, with ``limbs`` and ``bone_rms_m``, the RMS of its limb/torso
    bone lengths (independent of the posture). The depth of the body centre is the size in pixels over the
    focal length (robustly over time, :func:`robust_depth_track`); the centre lies on the camera ray
    through the weighted 2D keypoint centre; the world pose follows from T_world_cam_t.
    """
    from scipy.ndimage import median_filter

    T = S_px.shape[0]
    S = S_px - S_px.mean(axis=2, keepdims=True)
    if limbs is not None and bone_rms_m is not None:
        bl = body_limb_index(limbs)
        a = np.array([limbs[i][0] for i in bl])
        b = np.array([limbs[i][1] for i in bl])
        size_px = np.sqrt(np.mean(np.sum((S[:, :, a] - S[:, :, b]) ** 2, axis=1), axis=1))
        size_m = float(bone_rms_m)
    else:
        size_px = np.sqrt(np.mean(np.sum(S**2, axis=1), axis=1))
        size_m = float(body_rms_radius_m)
    f = 0.5 * (K[..., 0, 0] + K[..., 1, 1]) * np.ones(T)
    w = np.where(np.isfinite(W_px).all(1), weights, 0.0)
    depth = robust_depth_track(size_px, size_m, f, (w > 0).sum(-1))
    # metres per pixel unit: the per-frame size where it is sound, else the smoothed depth's
    with np.errstate(divide="ignore", invalid="ignore"):
        m_per_px = size_m / size_px
    fallback = depth / f
    ratio = np.where(np.isfinite(m_per_px) & (m_per_px > 0), m_per_px / fallback, np.inf)
    m_per_px = np.where(np.abs(np.log(ratio)) < np.log(1.5), m_per_px, fallback)
    m_per_px = median_filter(m_per_px, size=3, mode="nearest") if T >= 3 else m_per_px
    R_wc = T_world_cam[:, :3, :3]
    if frame == "world":
        S_w = S * m_per_px[:, None, None]
    else:
        S_w = R_wc @ (complete_rotation(R) @ S * m_per_px[:, None, None])
    Wz = np.where(np.isfinite(W_px), W_px, 0.0)
    c_px = np.einsum("tij,tj->ti", Wz, w) / np.maximum(w.sum(-1), 1e-9)[:, None]
    if (w.sum(-1) <= 0).any():  # no keypoint in a frame: its centre from the neighbours
        seen = w.sum(-1) > 0
        idx = np.arange(T)
        c_px = np.stack([np.interp(idx, idx[seen], c_px[seen, k]) for k in range(2)], -1) if seen.any() else c_px
    Kinv = np.linalg.inv(K) * np.ones((T, 1, 1))
    ray = np.einsum("tij,tj->ti", Kinv, np.concatenate([c_px, np.ones((T, 1))], 1))
    centre_cam = ray / ray[:, 2:3] * depth[:, None]
    centre_w = np.einsum("tij,tj->ti", R_wc, centre_cam) + T_world_cam[:, :3, 3]
    return np.swapaxes(S_w, 1, 2) + centre_w[:, None, :]


def perspective_bundle_adjust(
    W_px: np.ndarray,
    weights: np.ndarray,
    T_world_cam: np.ndarray,
    K: np.ndarray,
    X0: np.ndarray,
    limbs,
    dt_s: float = 1.0 / 24.0,
    cfg: PerspectiveConfig | None = None,
    t_s: np.ndarray | None = None,

) -> PerspectiveResult:
    """Perspective multi-frame BA in the world frame with known (estimated) camera poses.

    Args:
        W_px: (T, 2, J) keypoints, pixels (NaN where the weight is 0).
        weights: (T, J) >= 0 (confidence x inlier).
        T_world_cam: (T, 4, 4) camera->world poses (the drone's estimates), OpenCV optical camera axes.
        K: (3, 3) or (T, 3, 3) intrinsics.
        X0: (T, J, 3) initial world joints (e.g. :func:`orthographic_to_world` of the paper BA).
        limbs: sequence of (i, j) joint pairs.
        dt_s: frame period (used when ``t_s`` is not given).
        t_s: (T,) frame times in seconds, increasing: the smoothness terms then use the true, possibly uneven,
            frame intervals (a real camera drops and jitters frames: 14-600 ms between frames in a simulated
            flight at 8.7 Hz).
    Returns:
        :class:`PerspectiveResult`.
    """
    import torch

    cfg = cfg or PerspectiveConfig()
    W = np.asarray(W_px, dtype=float)
    T, _, J = W.shape
    X0 = np.asarray(X0, dtype=float)
    T_wc = np.asarray(T_world_cam, dtype=float)
    if X0.shape != (T, J, 3) or T_wc.shape != (T, 4, 4):
        raise SkycapError(f"perspective BA: X0 must be ({T}, {J}, 3) and T_world_cam ({T}, 4, 4); got {X0.shape}, {T_wc.shape}")
    if not np.all(np.isfinite(X0)):
        raise SkycapError("perspective BA: the initial joints X0 contain NaN/inf; initialise from a finite reconstruction")
    w = np.where(np.isfinite(W).all(1), np.asarray(weights, dtype=float), 0.0)
    W = np.where(np.isfinite(W), W, 0.0)
    Kt = np.broadcast_to(np.asarray(K, dtype=float), (T, 3, 3))
    dt = torch.float64
    tW = torch.tensor(np.swapaxes(W, 1, 2), dtype=dt)  # (T,J,2)
    tw = torch.tensor(w, dtype=dt)
    R_cw = torch.tensor(np.swapaxes(T_wc[:, :3, :3], 1, 2), dtype=dt)
    p_w = torch.tensor(T_wc[:, :3, 3], dtype=dt)
    fxy = torch.tensor(np.stack([Kt[:, 0, 0], Kt[:, 1, 1]], -1), dtype=dt)[:, None, :]
    cxy = torch.tensor(Kt[:, :2, 2], dtype=dt)[:, None, :]
    a = torch.tensor([l[0] for l in limbs])
    b = torch.tensor([l[1] for l in limbs])
    nL = len(limbs)
    body = body_limb_index(limbs)
    if len(body) == 0:
        raise SkycapError("perspective BA: no limb between body joints (COCO-17 >= 5); the size prior needs them")
    # The projective gauge: scaling frame t's joints about its camera centre p_t by one common factor e^s
    # leaves every projection unchanged. It is made explicit: Y (root + pose, bone lengths b_Y with RMS over the
    # body limbs fixed to body_bone_rms_m) is the body at the reference size, and the world joints are
    #     X_t = p_t + e^s (Y_t - p_t).
    # The reprojection, the articulation and the shape priors (pose smoothness, low rank) are evaluated on Y
    # (so they do not favour a small body: shrinking towards the cameras is not free); e^s is set by the size
    # prior s ~ N(0, size_prior_sigma^2) and by the parallax of the orbit through the smoothness of the world
    # root trajectory (rigidly scaling the body about moving camera centres bends its path by (1 - e^s) times
    # the camera's motion). A cheirality term keeps every joint at least min_depth_m in front of its camera.
    Xc0 = np.einsum("tji,tkj->tki", T_wc[:, :3, :3], X0 - T_wc[:, None, :3, 3])  # camera coordinates
    if np.median(Xc0[..., 2]) <= cfg.min_depth_m:
        raise SkycapError(f"perspective BA: the initial joints lie behind or within {cfg.min_depth_m} m of the cameras; "
                          "initialise from a reconstruction placed in front of the camera")  # fmt: skip
    bl0 = np.median(bone_lengths(X0, limbs), axis=0)
    s0 = float(np.log(np.sqrt(np.mean(bl0[body] ** 2)) / cfg.body_bone_rms_m))
    # Y0 = p + e^-s0 (X0 - p): the start at the reference size, same projections
    Y0 = T_wc[:, None, :3, 3] + np.exp(-s0) * (X0 - T_wc[:, None, :3, 3])
    c0 = Y0.mean(axis=1)
    # one flat parameter vector (root of Y (T,3), pose of Y (T,J,3), log bone lengths (nL,), camera corrections
    # (3T or 0), log depth factor d (1,), log scale s (1,)): contiguous for L-BFGS. The pose is parametrised in camera axes with the depth
    # axis divided by ``depth_gain`` (diagonal preconditioning: a joint's depth is far less constrained than its
    # image position).
    gain = torch.tensor([1.0, 1.0, cfg.depth_gain], dtype=dt)
    P0_cam = np.einsum("tji,tkj->tki", T_wc[:, :3, :3], Y0 - c0[:, None]) / np.array([1.0, 1.0, cfg.depth_gain])
    # per-frame camera rotation corrections (rotation vectors, camera axes) absorb the drone's pose error
    n_cam = 3 * T if cfg.camera_sigma_deg > 0 else 0
    theta = torch.tensor(np.concatenate([c0.ravel(), P0_cam.ravel(), np.log(np.maximum(bl0, 1e-3) * np.exp(-s0)),
                                         np.zeros(n_cam), [0.0, s0]]), dtype=dt, requires_grad=True)  # fmt: skip
    sig_cam = np.radians(cfg.camera_sigma_deg) if n_cam else 1.0
    R_wc = R_cw.transpose(1, 2)
    n1, n2 = 3 * T, 3 * T + 3 * T * J
    tbody = torch.tensor(body)
    # proportions prior: limbs with an adult reference length, scaled to the reference size body_bone_rms_m
    ref = ADULT_BONES_M
    if len(cfg.bone_prior_m):
        if len(cfg.bone_prior_m) != len(ADULT_BONES_M) or min(cfg.bone_prior_m) <= 0:
            raise SkycapError(f"perspective BA: bone_prior_m needs {len(ADULT_BONES_M)} positive lengths (limbs "
                              f"{list(ADULT_BONES_M)}), got {cfg.bone_prior_m}")  # fmt: skip
        ref = dict(zip(ADULT_BONES_M, map(float, cfg.bone_prior_m)))
    ref_rms = float(np.sqrt(np.mean(np.square(list(ref.values())))))
    pri = [(i, ref.get(tuple(l), ref.get((l[1], l[0]), np.nan))) for i, l in enumerate(limbs)]
    pri = [(i, v * cfg.body_bone_rms_m / ref_rms) for i, v in pri if np.isfinite(v)]
    t_pri_idx = torch.tensor([i for i, _ in pri], dtype=torch.long)
    t_pri_log = torch.tensor(np.log([v for _, v in pri]), dtype=dt)

    def unpack(th):
        """-> root of Y (T,3), centred pose of Y (T,J,3), bone lengths of Y (nL,), s (scalar)."""
        P = torch.einsum("tij,tkj->tki", R_wc, th[n1:n2].view(T, J, 3) * gain)
        P = P - P.mean(dim=1, keepdim=True)
        bY = th[n2 : n2 + nL].exp()
        bY = bY * (cfg.body_bone_rms_m / torch.sqrt((bY[tbody] ** 2).mean()))
        # th[-2] = d: a redundant coordinate moving every root of Y along its camera ray by one factor e^d (the
        # body's size fixed, so its image size changes: not the gauge). The depth of the body is badly
        # conditioned in per-frame root coordinates; this one direction makes it converge in a few iterations.
        root = p_w + th[-2].exp() * (th[:n1].view(T, 3) - p_w)
        return root, P, bY, th[-1]

    def camera_rotations(th):
        if not n_cam:
            return R_cw, None
        v = th[n2 + nL : n2 + nL + n_cam].view(T, 3)
        Z = torch.zeros(T, dtype=dt)
        skew = torch.stack([torch.stack([Z, -v[:, 2], v[:, 1]], -1), torch.stack([v[:, 2], Z, -v[:, 0]], -1),
                            torch.stack([-v[:, 1], v[:, 0], Z], -1)], 1)  # fmt: skip
        return torch.linalg.matrix_exp(skew) @ R_cw, v
    alpha = cfg.alpha * np.sqrt(T)
    if t_s is None:
        t_s = np.arange(T) * dt_s
    t_s = np.asarray(t_s, dtype=float)
    if t_s.shape != (T,) or (T > 1 and np.any(np.diff(t_s) <= 0)):
        raise SkycapError(f"perspective BA: t_s must be ({T},) strictly increasing frame times in seconds")
    h = np.diff(t_s)
    # second differences on an uneven grid: acc_t = 2 ((x_t+1 - x_t) / h1 - (x_t - x_t-1) / h0) / (h0 + h1)
    c_next = torch.tensor(2.0 / (h[1:] * (h[:-1] + h[1:])), dtype=dt)[:, None, None] if T >= 3 else None
    c_prev = torch.tensor(2.0 / (h[:-1] * (h[:-1] + h[1:])), dtype=dt)[:, None, None] if T >= 3 else None

    G = h_w = None
    if T >= 3 and cfg.parallax_tau_s > 0 and cfg.parallax_acc_sigma_mps2 > 0 and t_s[-1] - t_s[0] > 2 * cfg.parallax_tau_s:
        Gn = np.exp(-0.5 * ((t_s[:, None] - t_s[None, :]) / cfg.parallax_tau_s) ** 2)
        G = torch.tensor(Gn / Gn.sum(1, keepdims=True), dtype=dt)
        h_w = torch.tensor(0.5 * (h[:-1] + h[1:]) / cfg.parallax_tau_s, dtype=dt)[:, None]

    def acc(x):  # (T, ..., 3) -> (T-2, ..., 3) m/s^2
        xs = x if x.dim() == 3 else x[:, None, :]
        a_ = c_next * (xs[2:] - xs[1:-1]) - c_prev * (xs[1:-1] - xs[:-2])
        return a_ if x.dim() == 3 else a_[:, 0]
    eps = T * cfg.nuclear_eps_m**2  # smoothing: singular values below ~eps_m per frame are not pushed to 0

    def objective(sigma: float):
        root, P, bY, s = unpack(theta)
        Rc, v = camera_rotations(theta)
        Y = root[:, None, :] + P
        Yc = torch.einsum("tij,tkj->tki", Rc, Y - p_w[:, None, :])  # projections of Y = those of X
        z = Yc[..., 2:3]
        uv = fxy * Yc[..., :2] / z.clamp(min=cfg.min_depth_m) + cxy
        r2 = ((uv - tW) ** 2).sum(-1) / sigma**2
        F = (tw * r2 / (1.0 + r2)).sum()
        F = F + ((cfg.min_depth_m - z).clamp(min=0.0) ** 2).sum() / (0.1 * cfg.min_depth_m) ** 2  # cheirality
        if v is not None:
            F = F + (v**2).sum() / sig_cam**2
        lengths = (Y[:, a] - Y[:, b]).norm(dim=-1)
        F = F + ((lengths - bY) ** 2).sum() / cfg.bone_sigma_m**2
        F = F + s**2 / cfg.size_prior_sigma**2
        if cfg.bone_prior_sigma > 0 and len(pri):
            F = F + ((bY[t_pri_idx].log() - t_pri_log) ** 2).sum() / cfg.bone_prior_sigma**2
        if T >= 3:
            accP = acc(P)
            # per-frame smoothness of the root of Y (scale-free: absorbs the image-size noise of the depth and the
            # drone's position noise, whose effect on the image is a shift of the whole body)
            F = F + (accP**2).sum() / cfg.pose_acc_sigma_mps2**2 + (acc(root) ** 2).sum() / cfg.root_acc_sigma_mps2**2
        if G is not None:
            # parallax: the low-passed WORLD root path X_root = p + e^s (root - p) must move like a person (slowly
            # at the time scale tau). A wrong scale adds (e^s - 1) times the camera's orbit to it. The low-pass
            # removes the per-frame noise of the depth and of the camera positions, which would otherwise bias s
            # (their contribution would grow or shrink with e^s). Weighted by h/tau: ~one term per tau.
            rootX = p_w + s.exp() * (root - p_w)
            F = F + (h_w * acc(G @ rootX) ** 2).sum() / cfg.parallax_acc_sigma_mps2**2
        if alpha > 0:
            Pm = P.reshape(T, -1)
            lam = torch.linalg.eigvalsh(Pm.T @ Pm)
            F = F + alpha * torch.sqrt(lam.clamp(min=0.0) + eps).sum()
        return F

    sigmas = np.geomspace(cfg.robust_scale_start_px, cfg.robust_scale_px, max(cfg.stages, 1))
    hist = []
    iters = 0
    with torch.no_grad():
        f_start_final = float(objective(float(sigmas[-1])))
    for k, sigma in enumerate(sigmas):
        opt = torch.optim.LBFGS([theta], lr=1.0, max_iter=cfg.iters_per_stage, history_size=20,
                                tolerance_grad=1e-9, tolerance_change=1e-12, line_search_fn="strong_wolfe")  # fmt: skip

        def closure():
            opt.zero_grad()
            F = objective(float(sigma))
            F.backward()
            return F

        if k == 0:
            with torch.no_grad():
                hist.append(float(objective(float(sigma))))
        opt.step(closure)
        iters += int(opt.state[opt._params[0]].get("n_iter", 0))
        with torch.no_grad():
            hist.append(float(objective(float(sigma))))
    with torch.no_grad():
        root, P, bY, sc = unpack(theta)
        scale = float(sc.exp())
        X = (p_w[:, None, :] + scale * (root[:, None, :] + P - p_w[:, None, :])).numpy().copy()
        bones = (scale * bY).numpy().copy()
    log.debug("perspective BA: %d L-BFGS iterations, F %.4g -> %.4g (final sigma)", iters, f_start_final, hist[-1])
    return PerspectiveResult(X=X, bones_m=bones, objective=np.array(hist), objective_final_sigma=(f_start_final, hist[-1]),
                             iterations=iters, body_scale=scale)  # fmt: skip
