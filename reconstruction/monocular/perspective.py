"""Perspective bundle adjustment with the drone's known camera poses (beyond DroCap; the "product" variant).

The paper's BA (:mod:`reconstruction.monocular.ba`) models an orthographic camera whose rotation R_t is
unknown. A drone knows (up to its GPS/IMU error) where its camera is and where it points: ``T_world_cam``
per frame and the intrinsics ``K``. :func:`perspective_bundle_adjust` therefore optimises the joints
directly in the world frame (NED metres), X (T, J, 3) = root c_t (T, 3) + centred pose P_t (T, J, 3), and
the bone lengths b (nL,) (log-parametrised), minimising::

    F =   sum_tj w_tj rho_GM(||pi(K, T_world_cam_t, X_tj) - W_tj|| / sigma)      robust reprojection
        + (1 / s_b^2)   sum_tl (||X_ta - X_tb|| - b_l)^2                          articulation (rank-1 with a
                                                                                 constant time factor: metric)
        + (1 / s_P^2)   sum_t ||P_t+1 - 2 P_t + P_t-1||^2 dt^4                    pose smoothness (acceleration)
        + (1 / s_c^2)   sum_t ||c_t+1 - 2 c_t + c_t-1||^2 dt^4                    root smoothness (weak)
        + alpha sqrt(T) sum_i sqrt(lambda_i(P#^T P#) + T eps^2)                    smoothed nuclear norm of P#
        + (1 / s_r^2)   sum_t ||v_t||^2                                            camera corrections

where the camera rotation of frame t is exp([v_t]x) R_cw_t: a small per-frame correction v_t (T, 3) of
the drone's estimate, which absorbs its attitude and (to first order, as an image shift) position errors,
and rho_GM(r) = r^2 / (1 + r^2) (Geman-McClure, annealed from a wide ``sigma`` down to
``robust_scale_px``), w = confidence x inlier, P# stacks the centred poses as columns (the paper's low-rank
prior, here in metres in the world frame). The absolute size is not observable from one camera (the
smoothness and low-rank terms would shrink the body towards the cameras), so the body size is fixed: P is
normalised to the mean RMS joint radius r0 = ``body_rms_radius_m`` (a typical adult by default); the depth
of the body then follows from its image size. A redundant global scale about the camera centres is a
parameter too, so that the depth direction (badly conditioned in joint coordinates) converges quickly. The root
is only weakly smoothed because the drone's position error (white GPS noise) moves the projections
of the whole body; the pose smoothness is what makes depth observable as the camera moves around the person.

Solved with L-BFGS (strong Wolfe line search) in torch (CPU, float64), vectorised over frames.
:func:`orthographic_to_world` places the paper BA's result in the world to start from.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from reconstruction.monocular.linalg import complete_rotation
from skycap.errors import SkycapError

log = logging.getLogger(__name__)

__all__ = ["PerspectiveConfig", "PerspectiveResult", "perspective_bundle_adjust", "orthographic_to_world", "bone_lengths"]


@dataclasses.dataclass
class PerspectiveConfig:
    robust_scale_px: float = 8.0  # Geman-McClure scale sigma (final)
    robust_scale_start_px: float = 40.0  # first stage's sigma (annealing)
    bone_sigma_m: float = 0.01  # articulation: allowed bone-length variation
    pose_acc_sigma_mps2: float = 30.0  # pose smoothness: typical joint acceleration relative to the root
    root_acc_sigma_mps2: float = 10.0  # root smoothness (the body centre moves smoothly; also absorbs camera noise)
    alpha: float = 0.1  # smoothed nuclear norm weight (times sqrt(T)), metres
    body_rms_radius_m: float = 0.55  # r0: RMS distance of the 17 joints from their mean (CMU adults ~0.55 m)
    camera_sigma_deg: float = 3.0  # prior std of the per-frame camera rotation corrections (0 = trust the poses)
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


def bone_lengths(X: np.ndarray, limbs) -> np.ndarray:
    """(T, nL) bone lengths of joints X (T, J, 3)."""
    a = np.array([l[0] for l in limbs])
    b = np.array([l[1] for l in limbs])
    return np.linalg.norm(X[:, a] - X[:, b], axis=-1)


def orthographic_to_world(S_px, R, W_px, weights, T_world_cam, K, body_rms_radius_m, frame: str = "canonical") -> np.ndarray:
    """A BA's orthographic poses placed in the world: (T, J, 3) NED metres.

    Camera coordinates of pose t are Rbar_t S_t (Rbar = R completed to a rotation; with ``frame="world"``
    S_t is already in world axes, the extended BA), scaled to metres by the depth of the body centre over
    the focal length. The depth comes from the pose's size in pixels and the assumed body size
    ``body_rms_radius_m``, median-filtered over time (one body, smooth motion); the centre lies on the
    camera ray through the weighted 2D keypoint centre; the world pose follows from T_world_cam_t.
    """
    from scipy.ndimage import median_filter

    T = S_px.shape[0]
    S = S_px - S_px.mean(axis=2, keepdims=True)
    rad_px = np.sqrt(np.mean(np.sum(S**2, axis=1), axis=1))
    f = 0.5 * (K[..., 0, 0] + K[..., 1, 1]) * np.ones(T)
    depth = median_filter(f * body_rms_radius_m / np.maximum(rad_px, 1e-9), size=min(T, 25), mode="nearest")
    m_per_px = body_rms_radius_m / np.maximum(rad_px, 1e-9)
    R_wc = T_world_cam[:, :3, :3]
    if frame == "world":
        S_w = S * m_per_px[:, None, None]
    else:
        S_w = R_wc @ (complete_rotation(R) @ S * m_per_px[:, None, None])
    w = np.where(np.isfinite(W_px).all(1), weights, 0.0)
    Wz = np.where(np.isfinite(W_px), W_px, 0.0)
    c_px = np.einsum("tij,tj->ti", Wz, w) / np.maximum(w.sum(-1), 1e-9)[:, None]
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
) -> PerspectiveResult:
    """Perspective multi-frame BA in the world frame with known (estimated) camera poses.

    Args:
        W_px: (T, 2, J) keypoints, pixels (NaN where the weight is 0).
        weights: (T, J) >= 0 (confidence x inlier).
        T_world_cam: (T, 4, 4) camera->world poses (the drone's estimates), OpenCV optical camera axes.
        K: (3, 3) or (T, 3, 3) intrinsics.
        X0: (T, J, 3) initial world joints (e.g. :func:`orthographic_to_world` of the paper BA).
        limbs: sequence of (i, j) joint pairs.
        dt_s: frame period.
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
    c0 = X0.mean(axis=1)
    bl0 = np.median(bone_lengths(X0, limbs), axis=0)
    nL = len(bl0)
    # one flat parameter vector (root (T,3), pose (T,J,3), log bone lengths (nL,), log global scale about the
    # cameras (1,)): contiguous for L-BFGS. The global scale is redundant (X_t = p_t + e^s (root_t + P_t - p_t))
    # but moves the whole body along the camera rays in one coordinate: the depth/size direction, which is
    # badly conditioned in joint coordinates, converges quickly.
    # the pose is parametrised in camera axes with the depth axis divided by ``depth_gain`` (diagonal
    # preconditioning: a joint's depth is far less constrained than its image position)
    gain = torch.tensor([1.0, 1.0, cfg.depth_gain], dtype=dt)
    P0_cam = np.einsum("tji,tkj->tki", T_wc[:, :3, :3], X0 - c0[:, None]) / np.array([1.0, 1.0, cfg.depth_gain])
    # per-frame camera rotation corrections (rotation vectors, camera axes) absorb the drone's pose error
    n_cam = 3 * T if cfg.camera_sigma_deg > 0 else 0
    theta = torch.tensor(np.concatenate([c0.ravel(), P0_cam.ravel(), np.log(np.maximum(bl0, 1e-3)), np.zeros(n_cam), [0.0]]),
                         dtype=dt, requires_grad=True)  # fmt: skip
    sig_cam = np.radians(cfg.camera_sigma_deg) if n_cam else 1.0
    R_wc = R_cw.transpose(1, 2)
    n1, n2 = 3 * T, 3 * T + 3 * T * J

    def unpack(th):
        root = p_w + th[-1].exp() * (th[:n1].view(T, 3) - p_w)
        P = torch.einsum("tij,tkj->tki", R_wc, th[n1:n2].view(T, J, 3) * gain)
        P = P - P.mean(dim=1, keepdim=True)
        size = torch.sqrt((P**2).sum(-1).mean(-1) + 1e-12).mean()
        return root, P * (cfg.body_rms_radius_m / size), th[n2 : n2 + nL]

    def camera_rotations(th):
        if not n_cam:
            return R_cw, None
        v = th[n2 + nL : n2 + nL + n_cam].view(T, 3)
        Z = torch.zeros(T, dtype=dt)
        skew = torch.stack([torch.stack([Z, -v[:, 2], v[:, 1]], -1), torch.stack([v[:, 2], Z, -v[:, 0]], -1),
                            torch.stack([-v[:, 1], v[:, 0], Z], -1)], 1)  # fmt: skip
        return torch.linalg.matrix_exp(skew) @ R_cw, v
    alpha = cfg.alpha * np.sqrt(T)
    k4 = dt_s**4
    eps = T * cfg.nuclear_eps_m**2  # smoothing: singular values below ~eps_m per frame are not pushed to 0

    def objective(sigma: float):
        root, pose, logb = unpack(theta)
        Rc, v = camera_rotations(theta)
        P = pose - pose.mean(dim=1, keepdim=True)
        X = root[:, None, :] + P
        Xc = torch.einsum("tij,tkj->tki", Rc, X - p_w[:, None, :])
        z = Xc[..., 2:3].clamp(min=0.1)
        uv = fxy * Xc[..., :2] / z + cxy
        r2 = ((uv - tW) ** 2).sum(-1) / sigma**2
        F = (tw * r2 / (1.0 + r2)).sum()
        if v is not None:
            F = F + (v**2).sum() / sig_cam**2
        lengths = (X[:, a] - X[:, b]).norm(dim=-1)
        F = F + ((lengths - logb.exp()) ** 2).sum() / cfg.bone_sigma_m**2
        if T >= 3:
            accP = P[2:] - 2 * P[1:-1] + P[:-2]
            accc = root[2:] - 2 * root[1:-1] + root[:-2]
            F = F + (accP**2).sum() / (cfg.pose_acc_sigma_mps2**2 * k4) + (accc**2).sum() / (cfg.root_acc_sigma_mps2**2 * k4)
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
        root, pose, logb = unpack(theta)
        P = pose - pose.mean(dim=1, keepdim=True)
        X = (root[:, None, :] + P).numpy().copy()
        bones = logb.exp().numpy().copy()
    log.debug("perspective BA: %d L-BFGS iterations, F %.4g -> %.4g (final sigma)", iters, f_start_final, hist[-1])
    return PerspectiveResult(X=X, bones_m=bones, objective=np.array(hist), objective_final_sigma=(f_start_final, hist[-1]),
                             iterations=iters)  # fmt: skip
