"""Multi-frame bundle adjustment of DroCap (Zhou et al., ICRA 2018, Section II-C), vectorised over frames.

Minimises over poses S (T, 3, J), camera rotations R (T, 2, 3) with orthonormal rows, image translations
t (T, 2) and the auxiliary rank-1 matrix L (nL, T)::

    F = sum_t ||(W_t - R_t S_t - t_t 1^T) D_t^1/2||_F^2          reprojection (orthographic, D_t = weights)
        + gamma ||l(S) - L||_F^2                                  articulation: l(S)[:, t] = squared limb lengths
        + alpha ||S#||_*                                          low rank: column t of S# = vec(S_t)
      [ + eta_S sum_t ||S_t+1 - S_t||^2 + eta_R sum_t ||R_t+1 - R_t||^2      temporal smoothness   (extension)
        + beta sum_t ||R_t - Rhat_t||^2 ]                                    attitude prior on R_t (extension)

with S_t centred (mean over joints 0, as in the paper). ``gamma = 0`` (and no extension terms) is the
plain nuclear-norm NRSFM of the paper's ablation. Alternating updates, each of which never increases F:

* L: best rank-1 approximation of l(S) (SVD; paper), or (``L_update = "prior"``) the best rank-1 L = u v^T whose
  bone proportions u are the adult bone-length prior's (squared; :data:`reconstruction.monocular.perspective.
  ADULT_BONES_M`; face limbs fitted), v_t >= 0 the per-frame squared scale;
* t: weighted mean of the residual (closed form);
* R: second-order steps on the Stiefel manifold safeguarded by a majorise-minimise step (polar factor;
  :func:`stiefel_newton_step`), odd and even frames in turn when the rotation smoothness couples neighbours;
* S: monotone FISTA (Beck & Teboulle 2009) proximal-gradient steps with backtracking, whose proximal
  operator is singular value thresholding of S# (Nesterov acceleration as in the paper).

Articulation warm-up (default; ``BAConfig.paper()`` is the paper's order): gamma = 0 for ``warmup_iters``
outer iterations, then, if those poses' bone proportions are clearly closer to the adult prior's than the
init's (:func:`proportion_inconsistency` ratio <= ``warmup_accept_ratio``), gamma on from there; otherwise the
warm-up is discarded and the paper's BA runs from the init. Both minimise the same objective F; the
warm-up keeps a poor init's limb proportions from being locked into L in the first iterations.

Units: everything is scaled by the median RMS radius of the 2D poses (so alpha and gamma do not depend on
the image size); ``alpha`` is multiplied by sqrt(T) so its effect does not depend on the clip length.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from reconstruction.monocular.linalg import rank1_approx, stiefel_newton_step, svt

log = logging.getLogger(__name__)

__all__ = ["BAConfig", "BAResult", "bundle_adjust", "limb_index_arrays", "squared_limb_lengths", "prior_limb_proportions",
           "rank1_fixed_proportions", "proportion_inconsistency"]


@dataclasses.dataclass
class BAConfig:
    alpha: float = 0.05  # nuclear norm weight (times sqrt(T), normalised units)
    gamma: float = 1.0  # articulation weight (0 = the paper's "BA w/o art." ablation)
    outer_iters: int = 40
    prox_iters: int = 5  # proximal-gradient steps on S per outer iteration
    rot_iters: int = 1  # safeguarded Newton steps on R (Stiefel) per outer iteration
    tol: float = 1e-7  # stop when the relative decrease of F over an outer iteration is below this
    smooth_S: float = 0.0  # eta_S (extension)
    smooth_R: float = 0.0  # eta_R (extension)
    rot_prior: float = 0.0  # beta (extension; needs R_prior)
    # --- articulation warm-up and L's update (same objective; options beyond the paper's update order) ---
    L_update: str = "prior"  # "svd": L = best rank-1 approximation of l(S) (paper); "prior": L = u v^T, rank 1 with
    # the bone proportions u fixed to the adult bone-length prior (squared; limbs not in the prior are fitted), v_t fitted.
    # Applies after an accepted warm-up; the fallback (rejected warm-up) and warmup_iters = 0 use it as set.
    warmup_iters: int = 30  # adaptive schedule: first run this many iterations with gamma = 0 (0 = the paper's order)
    warmup_accept_ratio: float = 0.86  # keep the warm-up's poses only if their bone-proportion inconsistency is
    # <= this x the init's (else: the paper's BA from the init, L by SVD); 0 = always keep
    warmup_outer_iters: int = 40  # outer iterations with gamma after an accepted warm-up

    @classmethod
    def paper(cls, **kw) -> "BAConfig":
        """The paper's BA exactly: gamma from the first iteration, L by SVD."""
        return cls(**{"warmup_iters": 0, "L_update": "svd", **kw})

    def paper_order(self) -> "BAConfig":
        """This configuration with the paper's update order (no warm-up, L by SVD): what a discarded warm-up
        falls back to, and the pipeline's paper-order ablation."""
        return dataclasses.replace(self, warmup_iters=0, L_update="svd")


@dataclasses.dataclass
class BAResult:
    S: np.ndarray  # (T, 3, J) pixel units (orthographic), centred
    R: np.ndarray  # (T, 2, 3)
    t: np.ndarray  # (T, 2) pixels
    L: np.ndarray  # (nL, T) rank-1 squared limb lengths, normalised units
    objective: np.ndarray  # (n,) F after each outer iteration (normalised units), first = at the start; after an
    # accepted warm-up: the warm-up's (gamma = 0) history, then the main run's (each monotone; F jumps between them)
    scale_px: float  # the normalisation scale
    warmup_accepted: bool | None = None  # None: no warm-up ran; True/False: the adaptive schedule's choice


def limb_index_arrays(limbs) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([l[0] for l in limbs], dtype=int)
    b = np.array([l[1] for l in limbs], dtype=int)
    return a, b


def squared_limb_lengths(S: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """l(S): (nL, T) squared limb lengths of poses S (T, 3, J)."""
    d = S[:, :, a] - S[:, :, b]
    return np.sum(d * d, axis=1).T


def prior_limb_proportions(limbs) -> tuple[np.ndarray, np.ndarray]:
    """Squared adult bone lengths u (nL,) (m^2) of ``limbs`` and a mask (nL,) of those in the prior.

    From :data:`reconstruction.monocular.perspective.ADULT_BONES_M` (either joint order); limbs not in the
    prior (the face) get 0 and mask False.
    """
    from reconstruction.monocular.perspective import ADULT_BONES_M

    u = np.zeros(len(limbs))
    known = np.zeros(len(limbs), dtype=bool)
    for i, (p, q) in enumerate(limbs):
        m = ADULT_BONES_M.get((p, q), ADULT_BONES_M.get((q, p)))
        if m is not None:
            u[i], known[i] = m * m, True
    return u, known


def rank1_fixed_proportions(ell: np.ndarray, u: np.ndarray, known: np.ndarray, sweeps: int = 3) -> np.ndarray:
    """Best rank-1 L = u v^T to ``ell`` (nL, T) with u[known] fixed (block-coordinate: v, then u[~known]).

    Each half-step is an exact least-squares minimisation, so ||ell - L||_F never increases over the sweeps.
    v_t >= 0 (a squared scale). Returns L (nL, T).
    """
    u = np.array(u, dtype=float)
    v = None
    for _ in range(max(1, sweeps) if np.any(~known) else 1):
        v = np.maximum(u @ ell / max(float(u @ u), 1e-300), 0.0)  # (T,)
        if not np.any(~known):
            break
        vv = float(v @ v)
        if vv <= 0:
            break
        u[~known] = np.maximum(ell[~known] @ v / vv, 0.0)
    return np.outer(u, v)


class _Problem:
    def __init__(self, W, w, limbs, cfg: BAConfig, R_prior):
        self.W, self.w, self.cfg = W, w, cfg
        self.gamma = cfg.gamma
        self.a, self.b = limb_index_arrays(limbs)
        if cfg.L_update not in ("svd", "prior"):
            raise ValueError(f"BAConfig.L_update must be 'svd' or 'prior', not {cfg.L_update!r}")
        self.u_prior, self.u_known = prior_limb_proportions(limbs)
        if cfg.L_update == "prior" and cfg.gamma > 0 and len(self.a) and not np.any(self.u_known):
            raise ValueError("BAConfig.L_update='prior' needs limbs of the adult bone prior (COCO-17 limb bones)")
        self.T, _, self.J = W.shape
        self.inc = np.zeros((len(self.a), self.J))  # limb incidence: +1 at a, -1 at b
        self.inc[np.arange(len(self.a)), self.a] = 1.0
        self.inc[np.arange(len(self.a)), self.b] = -1.0
        self.alpha = cfg.alpha * np.sqrt(self.T)
        self.R_prior = R_prior

    # ----- smooth part in S (R, t, L fixed) -----
    def f_S(self, S, R, t, L, grad: bool = False):
        """Smooth part of F as a function of S; with ``grad`` also its gradient (projected on centred poses)."""
        E = self.W - R @ S - t[..., None]
        Ew = E * self.w[:, None, :]
        val = float(np.sum(E * Ew))
        g = -2.0 * np.swapaxes(R, 1, 2) @ Ew if grad else None
        if self.gamma > 0:
            d = S @ self.inc.T  # (T,3,nL) limb vectors
            D = np.sum(d * d, axis=1).T - L  # (nL, T)
            val += self.gamma * float(np.sum(D * D))
            if grad:
                g += (4.0 * self.gamma * d * D.T[:, None, :]) @ self.inc
        if self.cfg.smooth_S > 0:
            dS = S[1:] - S[:-1]
            val += self.cfg.smooth_S * float(np.sum(dS * dS))
            if grad:
                g[1:] += 2 * self.cfg.smooth_S * dS
                g[:-1] -= 2 * self.cfg.smooth_S * dS
        if not grad:
            return val
        return val, g - g.mean(axis=2, keepdims=True)  # stay on the centred subspace

    def grad_S(self, S, R, t, L):
        return self.f_S(S, R, t, L, grad=True)[1]

    def nuclear(self, S):
        lam = np.linalg.eigvalsh(S.reshape(self.T, -1).T @ S.reshape(self.T, -1))
        return float(np.sqrt(np.maximum(lam, 0.0)).sum())

    def objective(self, S, R, t, L, nuc=None):
        return self.f_S(S, R, t, L) + self.alpha * (self.nuclear(S) if nuc is None else nuc) + self.r_terms(R)

    def r_terms(self, R):
        val = 0.0
        if self.cfg.smooth_R > 0:
            val += self.cfg.smooth_R * float(np.sum((R[1:] - R[:-1]) ** 2))
        if self.cfg.rot_prior > 0 and self.R_prior is not None:
            val += self.cfg.rot_prior * float(np.sum((R - self.R_prior) ** 2))
        return val

    def prox(self, X, step):
        """SVT of S# with threshold alpha * step; returns (S, ||S#||_*)."""
        Y, nn = svt(X.reshape(self.T, -1).T, self.alpha * step, gram=True)
        return Y.T.reshape(X.shape), nn

    # ----- block updates -----
    def update_L(self, S):
        ell = squared_limb_lengths(S, self.a, self.b)
        if self.cfg.L_update == "prior":
            return rank1_fixed_proportions(ell, self.u_prior, self.u_known)
        return rank1_approx(ell)

    def update_t(self, S, R):
        ws = np.maximum(self.w.sum(-1), 1e-12)
        return np.einsum("tij,tj->ti", self.W - R @ S, self.w) / ws[:, None]

    def update_R(self, S, R, t):
        Wt = self.W - t[..., None]
        A = np.einsum("tij,tj,tkj->tik", S, self.w, S)
        C = np.einsum("tij,tj,tkj->tik", Wt, self.w, S)
        if self.cfg.rot_prior > 0 and self.R_prior is not None:
            C = C + self.cfg.rot_prior * self.R_prior
        eta = self.cfg.smooth_R
        for _ in range(self.cfg.rot_iters):
            if eta > 0:
                for parity in (0, 1):  # red-black: neighbours fixed while one parity moves
                    nb = np.zeros_like(R)
                    nb[1:] += R[:-1]
                    nb[:-1] += R[1:]
                    sel = slice(parity, None, 2)
                    R[sel] = stiefel_newton_step(R[sel], A[sel], C[sel] + eta * nb[sel])
            else:
                R = stiefel_newton_step(R, A, C)
        return R

    def update_S(self, S, R, t, L, mu, nuc):
        """Monotone FISTA with backtracking on S (``nuc`` = ||S#||_*). Returns S, mu, ||S#||_*."""
        x_prev = S
        x = S
        y = S
        tk = 1.0
        F_x = None
        for _ in range(self.cfg.prox_iters):
            fy, gy = self.f_S(y, R, t, L, grad=True)
            if F_x is None:
                F_x = fy + self.alpha * nuc
            while True:
                z, nn = self.prox(y - gy / mu, 1.0 / mu)
                dz = z - y
                fz = self.f_S(z, R, t, L)
                if fz <= fy + np.sum(gy * dz) + 0.5 * mu * np.sum(dz * dz) + 1e-12 * abs(fy):
                    break
                mu *= 2.0
            F_z = fz + self.alpha * nn
            tn = 0.5 * (1 + np.sqrt(1 + 4 * tk * tk))
            if F_z <= F_x:
                x_new, F_x, nuc = z, F_z, nn
            else:
                x_new = x
            y = x_new + (tk / tn) * (z - x_new) + ((tk - 1) / tn) * (x_new - x)
            x_prev, x, tk = x, x_new, tn
            mu *= 0.9  # let the step grow again
        del x_prev
        return x, mu, nuc, F_x


def proportion_inconsistency(S: np.ndarray, limbs) -> float:
    """Relative distance of the squared limb lengths l(S) (prior bones only) from the nearest L = u v^T with the
    adult bone proportions u: ||l - u v^T|| / ||l|| over the prior's limbs (0 = adult proportions in every frame,
    at any per-frame scale). S (T, 3, J) in any unit."""
    a, b = limb_index_arrays(limbs)
    u, known = prior_limb_proportions(limbs)
    if not np.any(known):
        raise ValueError("proportion_inconsistency needs limbs of the adult bone prior (COCO-17 limb bones)")
    ell = squared_limb_lengths(np.asarray(S, dtype=float), a, b)[known]
    L = rank1_fixed_proportions(ell, u[known], np.ones(int(known.sum()), dtype=bool))
    return float(np.linalg.norm(ell - L) / max(np.linalg.norm(ell), 1e-300))


def bundle_adjust(
    W_px: np.ndarray,
    weights: np.ndarray,
    S0: np.ndarray,
    R0: np.ndarray,
    limbs,
    cfg: BAConfig | None = None,
    R_prior: np.ndarray | None = None,
) -> BAResult:
    """DroCap multi-frame bundle adjustment from an initialisation.

    Args:
        W_px: (T, 2, J) 2D keypoints, pixels (NaN allowed where the weight is 0).
        weights: (T, J) >= 0 per-keypoint weights (confidence x inlier).
        S0: (T, 3, J) initial poses (pixel units of the orthographic camera); centred here.
        R0: (T, 2, 3) initial rotations.
        limbs: sequence of (i, j) joint pairs of the articulation term.
        R_prior: (T, 2, 3) rotation prior (e.g. from the drone's attitude and gimbal) for ``cfg.rot_prior``.
    Returns:
        :class:`BAResult`.
    """
    cfg = cfg or BAConfig()
    if cfg.warmup_iters > 0 and cfg.gamma > 0:
        return _warm_started(W_px, weights, S0, R0, limbs, cfg, R_prior)
    W = np.asarray(W_px, dtype=float)
    w = np.where(np.isfinite(W).all(1), np.asarray(weights, dtype=float), 0.0)
    W = np.where(np.isfinite(W), W, 0.0)
    ws = np.maximum(w.sum(-1), 1e-12)
    mean = np.einsum("tij,tj->ti", W, w) / ws[:, None]
    rad = np.sqrt(np.einsum("tij,tj->t", (W - mean[..., None]) ** 2, w) / ws)
    scale = float(np.median(rad[w.sum(-1) > 0])) if np.any(w.sum(-1) > 0) else 1.0
    W = W / scale
    S = np.asarray(S0, dtype=float) / scale
    S = S - S.mean(axis=2, keepdims=True)
    R = np.array(R0, dtype=float)
    prob = _Problem(W, w, limbs, cfg, R_prior)
    t = prob.update_t(S, R)
    L = prob.update_L(S) if prob.gamma > 0 else np.zeros((len(prob.a), prob.T))
    nuc = prob.nuclear(S)
    hist = [prob.objective(S, R, t, L, nuc)]
    mu = 2.0 * float(w.max(initial=1.0)) + 1.0
    for it in range(cfg.outer_iters):
        if prob.gamma > 0:
            L = prob.update_L(S)
        t = prob.update_t(S, R)
        R = prob.update_R(S, R, t)
        t = prob.update_t(S, R)
        S, mu, nuc, F_S = prob.update_S(S, R, t, L, mu, nuc)
        hist.append(F_S + prob.r_terms(R))
        if hist[-2] - hist[-1] < cfg.tol * abs(hist[-2]):
            break
    log.debug("BA: %d outer iterations, F %.4g -> %.4g", len(hist) - 1, hist[0], hist[-1])
    return BAResult(S=S * scale, R=R, t=t * scale, L=L, objective=np.array(hist), scale_px=scale)


def _warm_started(W_px, weights, S0, R0, limbs, cfg: BAConfig, R_prior) -> BAResult:
    """Adaptive articulation schedule: gamma = 0 for ``warmup_iters``; if that improved the poses' bone
    proportions enough (:func:`proportion_inconsistency` <= ``warmup_accept_ratio`` x the init's), continue
    from there with gamma (``warmup_outer_iters``); otherwise discard it and run the paper's BA from the init.

    Why: a poor init's limb proportions, locked into L from the first iteration, keep the BA from leaving
    them (002_10, wash self: 58.5 mm with gamma from the start, 37.5 after the warm-up); on short clips the
    nuclear norm alone usually wanders off (worse than the init; the ratio stays > 0.86) and the paper's order is
    kept. The threshold is empirical (8 CMU clips: accepted at 0.69-0.85, rejected at 0.87-1.05; see
    ``results/RESULTS.md``). Both branches
    minimise the paper's objective (the accepted one with L's proportions fixed to the adult prior when
    ``L_update = "prior"``).
    """
    base = dataclasses.replace(cfg, warmup_iters=0)
    warm = bundle_adjust(W_px, weights, S0, R0, limbs, dataclasses.replace(base, gamma=0.0, outer_iters=cfg.warmup_iters,
                                                                          tol=0.0), R_prior)  # fmt: skip
    ratio = proportion_inconsistency(warm.S, limbs) / max(proportion_inconsistency(S0, limbs), 1e-300)
    accept = cfg.warmup_accept_ratio <= 0 or ratio <= cfg.warmup_accept_ratio
    log.debug("BA warm-up: bone-proportion inconsistency ratio %.3f -> %s", ratio, "kept" if accept else "discarded")
    if accept:
        res = bundle_adjust(W_px, weights, warm.S, warm.R, limbs, dataclasses.replace(base, outer_iters=cfg.warmup_outer_iters),
                            R_prior)  # fmt: skip
        res.objective = np.concatenate([warm.objective, res.objective])
    else:
        res = bundle_adjust(W_px, weights, S0, R0, limbs, cfg.paper_order(), R_prior)
    res.warmup_accepted = bool(accept)
    return res
