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

* L: best rank-1 approximation of l(S) (SVD);
* t: weighted mean of the residual (closed form);
* R: second-order steps on the Stiefel manifold safeguarded by a majorise-minimise step (polar factor;
  :func:`stiefel_newton_step`), odd and even frames in turn when the rotation smoothness couples neighbours;
* S: monotone FISTA (Beck & Teboulle 2009) proximal-gradient steps with backtracking, whose proximal
  operator is singular value thresholding of S# (Nesterov acceleration as in the paper).

Units: everything is scaled by the median RMS radius of the 2D poses (so alpha and gamma do not depend on
the image size); ``alpha`` is multiplied by sqrt(T) so its effect does not depend on the clip length.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from reconstruction.monocular.linalg import rank1_approx, stiefel_newton_step, svt

log = logging.getLogger(__name__)

__all__ = ["BAConfig", "BAResult", "bundle_adjust", "limb_index_arrays", "squared_limb_lengths"]


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


@dataclasses.dataclass
class BAResult:
    S: np.ndarray  # (T, 3, J) pixel units (orthographic), centred
    R: np.ndarray  # (T, 2, 3)
    t: np.ndarray  # (T, 2) pixels
    L: np.ndarray  # (nL, T) rank-1 squared limb lengths, normalised units
    objective: np.ndarray  # (n,) F after each outer iteration (normalised units), first = at the start
    scale_px: float  # the normalisation scale


def limb_index_arrays(limbs) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([l[0] for l in limbs], dtype=int)
    b = np.array([l[1] for l in limbs], dtype=int)
    return a, b


def squared_limb_lengths(S: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """l(S): (nL, T) squared limb lengths of poses S (T, 3, J)."""
    d = S[:, :, a] - S[:, :, b]
    return np.sum(d * d, axis=1).T


class _Problem:
    def __init__(self, W, w, limbs, cfg: BAConfig, R_prior):
        self.W, self.w, self.cfg = W, w, cfg
        self.a, self.b = limb_index_arrays(limbs)
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
        if self.cfg.gamma > 0:
            d = S @ self.inc.T  # (T,3,nL) limb vectors
            D = np.sum(d * d, axis=1).T - L  # (nL, T)
            val += self.cfg.gamma * float(np.sum(D * D))
            if grad:
                g += (4.0 * self.cfg.gamma * d * D.T[:, None, :]) @ self.inc
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
    L = rank1_approx(squared_limb_lengths(S, prob.a, prob.b)) if cfg.gamma > 0 else np.zeros((len(prob.a), prob.T))
    nuc = prob.nuclear(S)
    hist = [prob.objective(S, R, t, L, nuc)]
    mu = 2.0 * float(w.max(initial=1.0)) + 1.0
    for it in range(cfg.outer_iters):
        if cfg.gamma > 0:
            L = rank1_approx(squared_limb_lengths(S, prob.a, prob.b))
        t = prob.update_t(S, R)
        R = prob.update_R(S, R, t)
        t = prob.update_t(S, R)
        S, mu, nuc, F_S = prob.update_S(S, R, t, L, mu, nuc)
        hist.append(F_S + prob.r_terms(R))
        if hist[-2] - hist[-1] < cfg.tol * abs(hist[-2]):
            break
    log.debug("BA: %d outer iterations, F %.4g -> %.4g", len(hist) - 1, hist[0], hist[-1])
    return BAResult(S=S * scale, R=R, t=t * scale, L=L, objective=np.array(hist), scale_px=scale)
