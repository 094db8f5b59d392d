"""Single-frame initialisation: 3D pose and camera rotation from one frame's 2D keypoints.

Model (orthographic, per frame t): ``W_t ~= R_t S_t + t_t 1^T`` with ``S_t = sum_k c_tk B_k`` from the pose
dictionary, ``R_t`` (2, 3) with orthonormal rows. Steps, all vectorised over frames:

1. **Convex relaxation** (Zhou, Zhu, Leonardos, Daniilidis, PAMI 2017): with ``M_k = c_k R_k`` solve
   ``min_M 1/2 ||(W - sum_k M_k B_k - t 1^T) D^1/2||_F^2 + lam sum_k ||M_k||_2`` by ADMM, whose
   M-step is the proximal operator of the spectral norm (:func:`prox_spectral_2x3`).
2. **Refinement** of the non-convex model with one rotation per frame: alternate the rotation
   (majorise-minimise on the Stiefel manifold), the translation (closed form) and the sparse
   coefficients (lasso by FISTA), starting from the rotation of the strongest atom.
3. **Robustness**: joints are weighted by their detector confidence times a Geman–McClure weight of their
   residual, re-estimated between rounds (IRLS); joints whose residual stays large are flagged as
   outliers (``inlier`` False) so later stages can ignore or correct them.

Units: the input is in pixels; internally each frame is centred and scaled to unit RMS radius, and the
results are returned in pixel units again (``S`` is in pixels of the orthographic camera).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from reconstruction.monocular.dictionary import PoseDictionary, canonical_rotation, sparse_code
from reconstruction.monocular.linalg import complete_rotation, polar_2x3, prox_spectral_2x3, stiefel_mm_step

__all__ = ["InitConfig", "InitResult", "initialise"]


@dataclasses.dataclass
class InitConfig:
    lam_convex: float = 0.3  # spectral-norm weight of the convex relaxation (normalised units)
    rho: float = 1.0  # ADMM penalty
    admm_iters: int = 150
    lam_refine: float = 0.02  # l1 weight of the coefficients in the refinement
    refine_iters: int = 20  # alternations (R, t, c)
    lasso_iters: int = 30  # FISTA steps per coefficient update
    robust_rounds: int = 4  # IRLS refinement rounds after the convex start
    robust_sigma: float = 0.15  # Geman-McClure scale (normalised units: body RMS radius = 1)
    outlier_threshold: float = 0.35  # residual beyond which a joint is flagged an outlier
    resolve_flips: bool = True  # second (depth-reflected) hypothesis per frame + temporal Viterbi choice
    flip_pairwise_weight: float = 1.0  # weight of the temporal term vs the per-frame fit in the Viterbi
    noise_sigma_mult: float = 1.0  # with ``noise_px`` given: Geman-McClure scale >= this x noise_px (pixels)
    noise_outlier_mult: float = 2.5  # with ``noise_px`` given: outlier threshold >= this x noise_px (pixels)


@dataclasses.dataclass
class InitResult:
    S: np.ndarray  # (T, 3, J) pose in the dictionary's canonical frame, pixel units
    R: np.ndarray  # (T, 2, 3) camera rotation rows (orthographic)
    t: np.ndarray  # (T, 2) image translation, pixels
    coeffs: np.ndarray  # (T, K)
    weights: np.ndarray  # (T, J) final robust weights in [0, 1]
    inlier: np.ndarray  # (T, J) bool: detected and consistent with the estimate
    residual_px: np.ndarray  # (T, J) reprojection residual in pixels

    def reprojection(self) -> np.ndarray:
        """(T, 2, J) model keypoints in pixels."""
        return self.R @ self.S + self.t[..., None]


def _normalise(W: np.ndarray, w: np.ndarray):
    ws = np.maximum(w.sum(-1), 1e-9)
    mean = np.einsum("tij,tj->ti", W, w) / ws[:, None]
    Wc = W - mean[..., None]
    scale = np.sqrt(np.einsum("tij,tj->t", Wc**2, w) / ws)
    scale = np.where(scale > 1e-9, scale, 1.0)
    return Wc / scale[:, None, None], mean, scale


def _convex(Wn: np.ndarray, w: np.ndarray, B: np.ndarray, cfg: InitConfig):
    """ADMM for the convex relaxation. Wn (T,2,J), w (T,J), B (K,3,J) -> M (T,K,2,3).

    The translation is eliminated in closed form (weighted centring: residual E -> E Q with
    Q = (I - 1 w^T / sum w) D^1/2), and the (3K x 3K) linear system of the M-step is solved with the
    Woodbury identity through a (J x J) one per frame.
    """
    T, _, J = Wn.shape
    K = B.shape[0]
    ws = np.maximum(w.sum(-1), 1e-9)
    P = np.eye(J)[None] - (w / ws[:, None])[:, None, :]  # (T,J,J): rows i -> e_i - w/sum(w) ... applied on the right
    P = np.swapaxes(P, 1, 2)  # E @ P subtracts the weighted mean column
    Q = P * np.sqrt(w)[:, None, :]  # (T,J,J) = P D^1/2
    F = np.einsum("aj,tjn->tan", B.reshape(3 * K, J), Q)  # (T,3K,J)
    H = np.linalg.inv(cfg.rho * np.eye(J)[None] + np.swapaxes(F, 1, 2) @ F)  # (T,J,J)
    WQ = Wn @ Q  # (T,2,J)
    WQF = WQ @ np.swapaxes(F, 1, 2)  # (T,2,3K)

    def solve(rhs):  # rhs (T,2,3K) @ (F F^T + rho I)^-1
        return (rhs - ((rhs @ F) @ H) @ np.swapaxes(F, 1, 2)) / cfg.rho

    M = np.zeros((T, K, 2, 3))
    U = np.zeros_like(M)
    tau = cfg.lam_convex / cfg.rho
    for _ in range(cfg.admm_iters):
        rhs = WQF + cfg.rho * (M - U).transpose(0, 2, 1, 3).reshape(T, 2, 3 * K)
        Zm = solve(rhs).reshape(T, 2, K, 3).transpose(0, 2, 1, 3)
        M = prox_spectral_2x3(Zm + U, tau)
        U = U + Zm - M
    return M


def _lasso(W: np.ndarray, w: np.ndarray, R: np.ndarray, B: np.ndarray, lam: float, iters: int, c0: np.ndarray):
    """Batched lasso for the coefficients with R fixed: min 1/2 ||(W - R sum c_k B_k) D^1/2||^2 + lam|c|_1.

    W (T,2,J) already translated, w (T,J), R (T,2,3), B (K,3,J), c0 (T,K) -> c (T,K).
    """
    A = np.einsum("tia,kaj->tkij", R, B)  # (T,K,2,J)
    Aw = A * np.sqrt(w)[:, None, None, :]
    T, K = c0.shape
    Af = Aw.reshape(T, K, -1)
    G = Af @ np.swapaxes(Af, 1, 2)  # (T,K,K)
    b = np.einsum("tkn,tn->tk", Af, (W * np.sqrt(w)[:, None, :]).reshape(T, -1))
    L = np.linalg.eigvalsh(G)[:, -1] + 1e-9
    c, y, tk = c0.copy(), c0.copy(), 1.0
    for _ in range(iters):
        g = np.einsum("tkl,tl->tk", G, y) - b
        z = y - g / L[:, None]
        cn = np.sign(z) * np.maximum(np.abs(z) - lam / L[:, None], 0.0)
        tn = 0.5 * (1 + np.sqrt(1 + 4 * tk * tk))
        y = cn + ((tk - 1) / tn) * (cn - c)
        c, tk = cn, tn
    return c


def _refine(Wn, w, B, R, c, cfg: InitConfig):
    """Alternate translation, rotation (Stiefel MM) and coefficients. Returns R, t, c."""
    for _ in range(cfg.refine_iters):
        S = np.einsum("tk,kij->tij", c, B)
        ws = np.maximum(w.sum(-1), 1e-9)
        t = np.einsum("tij,tj->ti", Wn - R @ S, w) / ws[:, None]
        Wt = Wn - t[..., None]
        A = np.einsum("tij,tj,tkj->tik", S, w, S)
        C = np.einsum("tij,tj,tkj->tik", Wt, w, S)
        for _ in range(3):
            R = stiefel_mm_step(R, A, C)
        c = _lasso(Wt, w, R, B, cfg.lam_refine, cfg.lasso_iters, c)
    S = np.einsum("tk,kij->tij", c, B)
    t = np.einsum("tij,tj->ti", Wn - R @ S, w) / np.maximum(w.sum(-1), 1e-9)[:, None]
    return R, t, c


def _frame_costs(Wn, w, B, R, t, c, lam):
    S = np.einsum("tk,kij->tij", c, B)
    E = Wn - R @ S - t[..., None]
    return np.einsum("tij,tj->t", E * E, w) + lam * np.abs(c).sum(-1), complete_rotation(R) @ S


def _resolve_flips(Wn, w, B, R, t, c, cfg: InitConfig):
    """Depth-reflection ambiguity of one orthographic view: build, per frame, the second interpretation
    (the pose mirrored through the image plane, re-fitted to the dictionary and the 2D keypoints) and pick
    one interpretation per frame by dynamic programming (Viterbi), trading each frame's fit (weighted
    reprojection error + l1) against the change of the camera-frame pose between consecutive frames.
    Returns R, t, c (T, ...)."""
    T = Wn.shape[0]
    K = B.shape[0]
    S = np.einsum("tk,kij->tij", c, B)
    Rb = complete_rotation(R)
    F = np.diag([1.0, 1.0, -1.0])
    S_ref = np.swapaxes(Rb, 1, 2) @ F @ Rb @ S  # same image, mirrored depth (canonical coordinates)
    Q = canonical_rotation(np.swapaxes(S_ref, 1, 2))
    S_B = Q @ S_ref
    c_B = sparse_code(S_B.reshape(T, -1), B.reshape(K, -1), cfg.lam_refine, iters=100)
    R_B = (Rb @ np.swapaxes(Q, 1, 2))[:, :2]
    R_B, t_B, c_B = _refine(Wn, w, B, R_B, c_B, cfg)
    u_A, P_A = _frame_costs(Wn, w, B, R, t, c, cfg.lam_refine)
    u_B, P_B = _frame_costs(Wn, w, B, R_B, t_B, c_B, cfg.lam_refine)
    unary = np.stack([u_A, u_B], 1)  # (T,2)
    P = np.stack([P_A, P_B], 1)  # (T,2,3,J)
    pair = np.sum((P[1:, :, None] - P[:-1, None, :]) ** 2, axis=(-1, -2))  # (T-1, 2, 2) [t, h_t, h_t-1]
    # truncated: a cut (scene change, dropped frames) must not force a choice on its neighbours
    cap = 10.0 * np.median(pair.min(axis=(1, 2))) + 1e-9
    pair = np.minimum(pair, cap) * cfg.flip_pairwise_weight
    cost = unary[0].copy()
    back = np.zeros((T, 2), dtype=int)
    for i in range(1, T):
        tot = cost[None, :] + pair[i - 1]  # (h_t, h_t-1)
        back[i] = np.argmin(tot, axis=1)
        cost = unary[i] + tot[np.arange(2), back[i]]
    h = np.zeros(T, dtype=int)
    h[-1] = int(np.argmin(cost))
    for i in range(T - 1, 0, -1):
        h[i - 1] = back[i, h[i]]
    pick = (h == 1)
    R = np.where(pick[:, None, None], R_B, R)
    t = np.where(pick[:, None], t_B, t)
    c = np.where(pick[:, None], c_B, c)
    return R, t, c


def initialise(
    W_px: np.ndarray,
    confidence: np.ndarray | None,
    dictionary: PoseDictionary,
    cfg: InitConfig | None = None,
    noise_px: float = 0.0,
) -> InitResult:
    """Single-frame 3D pose + camera rotation for every frame (independently, vectorised).

    Args:
        W_px: (T, 2, J) 2D keypoints in pixels (NaN allowed where confidence is 0).
        confidence: (T, J) detector confidences in [0, 1] (0 = missing); None = all ones.
        dictionary: pose dictionary with J joints.
        noise_px: typical keypoint error in pixels (e.g. :func:`reconstruction.monocular.tracks.track_noise_px`),
            0 = unknown. The robust scale and the outlier threshold are relative to the person's image size
            (``robust_sigma``, ``outlier_threshold``); for a small (far) person they are raised to
            ``noise_sigma_mult`` / ``noise_outlier_mult`` times ``noise_px``, so that ordinary detector noise
            is not taken for outliers.
    Returns:
        :class:`InitResult` (pixel units).
    """
    cfg = cfg or InitConfig()
    W_px = np.asarray(W_px, dtype=float)
    T, two, J = W_px.shape
    if two != 2 or J != dictionary.num_joints:
        raise ValueError(f"W_px must be (T, 2, {dictionary.num_joints}), got {W_px.shape}")
    conf = np.ones((T, J)) if confidence is None else np.clip(np.asarray(confidence, dtype=float), 0.0, 1.0)
    conf = np.where(np.isfinite(W_px).all(1), conf, 0.0)
    W_px = np.where(np.isfinite(W_px), W_px, 0.0)
    B = dictionary.bases
    w = conf.copy()
    Wn, mean, scale = _normalise(W_px, w)
    M = _convex(Wn, w, B, cfg)
    # Each M_k ~ c_k R_k: strength = mean singular value, rotation = polar factor.
    strength = np.linalg.svd(M, compute_uv=False).mean(-1)  # (T,K)
    R = polar_2x3(M[np.arange(T), np.argmax(strength, axis=1)])
    c = np.einsum("tkij,tij->tk", M, R) / 2.0  # project each M_k on R: c_k = <M_k, R> / 2
    R, t, c = _refine(Wn, w, B, R, c, cfg)
    # IRLS with an annealed Geman-McClure scale: refit with robust weights, from wide to narrow.
    # per-frame floors from the pixel noise (normalised units: divided by the frame's image scale)
    sig_floor = (cfg.noise_sigma_mult * max(noise_px, 0.0) / scale)[:, None]  # (T,1)
    thr = np.maximum(cfg.outlier_threshold, (cfg.noise_outlier_mult * max(noise_px, 0.0) / scale)[:, None])
    sigmas = np.geomspace(4 * cfg.robust_sigma, cfg.robust_sigma, max(1, cfg.robust_rounds))
    for sigma0 in sigmas:
        sigma = np.maximum(sigma0, sig_floor)
        res = np.linalg.norm(Wn - (R @ np.einsum("tk,kij->tij", c, B) + t[..., None]), axis=1)  # (T,J)
        w = conf * (sigma**2 / (sigma**2 + res**2)) ** 2
        R, t, c = _refine(Wn, w, B, R, c, cfg)
    if cfg.resolve_flips and T > 1:
        R, t, c = _resolve_flips(Wn, w, B, R, t, c, cfg)
    res = np.linalg.norm(Wn - (R @ np.einsum("tk,kij->tij", c, B) + t[..., None]), axis=1)
    if dictionary.mean_pose is not None:
        # (R, c) and (-R, -c) project identically; keep the upright one (positive overlap with the mean pose)
        sgn = np.where(np.einsum("tk,kij,ij->t", c, B, dictionary.mean_pose) < 0, -1.0, 1.0)
        R, c = R * sgn[:, None, None], c * sgn[:, None]
    inlier = (conf > 0) & (res < thr)
    S = np.einsum("tk,kij->tij", c, B) * scale[:, None, None]
    t_px = t * scale[:, None] + mean
    return InitResult(
        S=S, R=R, t=t_px, coeffs=c * scale[:, None], weights=w, inlier=inlier, residual_px=res * scale[:, None]
    )
