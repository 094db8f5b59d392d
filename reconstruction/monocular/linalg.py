"""Small vectorised linear-algebra pieces of the monocular pipeline (pure numpy, batched).

* :func:`svt` — singular value thresholding, the proximal operator of ``tau * ||X||_*``.
* :func:`prox_spectral_2x3` — proximal operator of ``tau * ||M||_2`` (spectral norm) for a batch of
  2x3 matrices (the convex relaxation of Zhou et al., PAMI 2017).
* :func:`project_l1_ball` — Euclidean projection of vectors onto the l1 ball.
* :func:`rank1_approx` — best rank-1 approximation (the ``L`` update of DroCap's articulation term).
* :func:`polar_2x3` — the nearest matrix with orthonormal rows (Stiefel manifold St(3, 2)).
* :func:`stiefel_mm_step` — one majorise-minimise step of ``min_R ||(W - R S) D^1/2||^2 - 2 tr(R^T G)``
  over R with orthonormal rows; never increases the objective.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "svt",
    "project_l1_ball",
    "prox_spectral_2x3",
    "rank1_approx",
    "polar_2x3",
    "complete_rotation",
    "stiefel_mm_step",
]


def svt(X: np.ndarray, tau: float, gram: bool = False) -> tuple[np.ndarray, float]:
    """Singular value thresholding: argmin_Y 1/2 ||Y - X||_F^2 + tau ||Y||_*.

    Args:
        X: (m, n) matrix.
        tau: threshold >= 0.
        gram: for m << n, use the eigen-decomposition of the (m, m) Gram matrix X X^T (about 5x faster
            than the SVD for the 51 x 300 pose matrices; singular values below about 1e-8 of the largest
            lose relative precision, which does not matter once they are thresholded).
    Returns:
        (Y (m, n), ||Y||_* ) — the shrunk matrix and its nuclear norm.
    """
    if gram and X.shape[0] < X.shape[1]:
        lam, U = np.linalg.eigh(X @ X.T)
        s = np.sqrt(np.maximum(lam, 0.0))
        keep = s > tau
        ratio = np.where(keep, (s - tau) / np.where(keep, s, 1.0), 0.0)
        Y = (U * ratio) @ (U.T @ X)
        return Y, float(np.sum(np.where(keep, s - tau, 0.0)))
    U, s, Vt = np.linalg.svd(X, full_matrices=False)
    s = np.maximum(s - tau, 0.0)
    k = int(np.count_nonzero(s))
    Y = (U[:, :k] * s[:k]) @ Vt[:k]
    return Y, float(s.sum())


def project_l1_ball(v: np.ndarray, radius) -> np.ndarray:
    """Project each row of ``v`` (..., n) onto {x : ||x||_1 <= radius} (Duchi et al. 2008), vectorised.

    ``radius`` is a scalar or broadcastable to v.shape[:-1]. Rows already inside are unchanged.
    """
    v = np.asarray(v, dtype=float)
    r = np.broadcast_to(np.asarray(radius, dtype=float), v.shape[:-1])
    a = np.abs(v)
    inside = a.sum(-1) <= r
    u = -np.sort(-a, axis=-1)
    css = np.cumsum(u, axis=-1)
    n = v.shape[-1]
    k = np.arange(1, n + 1)
    cond = u - (css - r[..., None]) / k > 0
    rho = n - 1 - np.argmax(cond[..., ::-1], axis=-1)  # last index where cond holds
    theta = (np.take_along_axis(css, rho[..., None], -1)[..., 0] - r) / (rho + 1)
    w = np.sign(v) * np.maximum(a - np.maximum(theta, 0.0)[..., None], 0.0)
    return np.where(inside[..., None], v, w)


def _svd_2x3(M: np.ndarray):
    """Batched SVD of (..., 2, 3) via the closed-form eigen-decomposition of M M^T (2x2).

    Returns U (..., 2, 2), s (..., 2) descending, and M itself (for V^T = diag(1/s) U^T M).
    """
    A = M @ np.swapaxes(M, -1, -2)
    a, b, c = A[..., 0, 0], A[..., 0, 1], A[..., 1, 1]
    half_tr = 0.5 * (a + c)
    disc = np.sqrt(np.maximum(0.25 * (a - c) ** 2 + b * b, 0.0))
    l1 = half_tr + disc
    l2 = np.maximum(half_tr - disc, 0.0)
    # eigenvector of l1: angle phi with tan(2 phi) = 2b / (a - c)
    phi = 0.5 * np.arctan2(2.0 * b, a - c)
    cph, sph = np.cos(phi), np.sin(phi)
    U = np.stack([np.stack([cph, -sph], -1), np.stack([sph, cph], -1)], -2)
    s = np.sqrt(np.stack([l1, l2], -1))
    return U, s


def prox_spectral_2x3(M: np.ndarray, tau) -> np.ndarray:
    """argmin_Y 1/2 ||Y - M||_F^2 + tau ||Y||_2 for a batch of 2x3 matrices (..., 2, 3).

    The singular values s become s - P_{l1 ball(tau)}(s) (Moreau decomposition: the dual norm of the
    spectral norm is the nuclear norm). ``tau`` scalar or shaped like M.shape[:-2].
    """
    U, s = _svd_2x3(M)
    s_new = s - project_l1_ball(s, tau)
    ratio = np.where(s > 1e-12, s_new / np.maximum(s, 1e-12), 0.0)
    # Y = U diag(s_new) V^T = U diag(s_new / s) U^T M
    P = (U * ratio[..., None, :]) @ np.swapaxes(U, -1, -2)
    return P @ M


def rank1_approx(X: np.ndarray) -> np.ndarray:
    """Best rank-1 approximation of X (m, n) in Frobenius norm (Eckart–Young), by SVD."""
    U, s, Vt = np.linalg.svd(X, full_matrices=False)
    return s[0] * np.outer(U[:, 0], Vt[0])


def polar_2x3(M: np.ndarray) -> np.ndarray:
    """Nearest (Frobenius) matrices with orthonormal rows to a batch M (..., 2, 3): U V^T of the SVD.

    Computed in closed form as (M M^T)^(-1/2) M through the 2x2 eigen-decomposition (numpy's batched SVD
    is slow for many tiny matrices); rank-deficient inputs fall back to numpy's SVD.
    """
    M = np.asarray(M, dtype=float)
    U, s = _svd_2x3(M)
    ok = s[..., 1] > 1e-9 * np.maximum(s[..., 0], 1e-300)
    inv = np.where(ok[..., None], 1.0 / np.where(ok[..., None], s, 1.0), 0.0)
    out = ((U * inv[..., None, :]) @ np.swapaxes(U, -1, -2)) @ M
    if not np.all(ok):
        Ub, _, Vt = np.linalg.svd(M[~ok], full_matrices=False)
        out[~ok] = Ub @ Vt
    return out


def complete_rotation(R2: np.ndarray) -> np.ndarray:
    """(..., 2, 3) orthonormal rows -> (..., 3, 3) rotation with third row r1 x r2."""
    return np.concatenate([R2, np.cross(R2[..., 0, :], R2[..., 1, :])[..., None, :]], axis=-2)


def lambda_max_sym3(A: np.ndarray) -> np.ndarray:
    """Largest eigenvalue of symmetric 3x3 matrices (..., 3, 3), closed form (trigonometric; Smith 1961)."""
    q = np.trace(A, axis1=-2, axis2=-1) / 3.0
    off = A[..., 0, 1] ** 2 + A[..., 0, 2] ** 2 + A[..., 1, 2] ** 2
    d0, d1, d2 = A[..., 0, 0] - q, A[..., 1, 1] - q, A[..., 2, 2] - q
    p = np.sqrt(np.maximum((d0**2 + d1**2 + d2**2 + 2 * off) / 6.0, 0.0))
    safe = p > 1e-300
    ps = np.where(safe, p, 1.0)
    B = (A - q[..., None, None] * np.eye(3)) / ps[..., None, None]
    r = np.clip(np.linalg.det(B) / 2.0, -1.0, 1.0)
    phi = np.arccos(r) / 3.0
    return np.where(safe, q + 2.0 * p * np.cos(phi), q)


def stiefel_mm_step(R: np.ndarray, A: np.ndarray, C: np.ndarray) -> np.ndarray:
    """One majorise-minimise step for min_R tr(R A R^T) - 2 tr(R C^T), R (..., 2, 3) with R R^T = I.

    With ``A = S D S^T`` (3x3, PSD) and ``C = (W - t) D S^T`` (2x3) this is the weighted reprojection
    error ||(W - t - R S) D^1/2||_F^2 up to a constant. Because tr(R (A - lam I) R^T) is concave for
    lam >= lambda_max(A) and tr(R R^T) = 2 is constant, linearising it at the current R gives a
    majoriser whose minimiser is the polar factor of C + R (lam I - A); the objective never increases.

    Shapes: R (..., 2, 3), A (..., 3, 3), C (..., 2, 3) -> (..., 2, 3).
    """
    lam = lambda_max_sym3(A) * (1.0 + 1e-9) + 1e-300 if A.shape[-1] == 3 else np.linalg.eigvalsh(A)[..., -1]
    target = C + lam[..., None, None] * R - R @ A
    return polar_2x3(target)


_GENERATORS = np.array(
    [[[0, 0, 0], [0, 0, -1], [0, 1, 0]], [[0, 0, 1], [0, 0, 0], [-1, 0, 0]], [[0, -1, 0], [1, 0, 0], [0, 0, 0]]], dtype=float
)


def stiefel_quadratic(R: np.ndarray, A: np.ndarray, C: np.ndarray) -> np.ndarray:
    """tr(R A R^T) - 2 tr(R C^T) per batch element (...,)."""
    return np.einsum("...ij,...jk,...ik->...", R, A, R) - 2.0 * np.sum(R * C, axis=(-1, -2))


def stiefel_newton_step(R: np.ndarray, A: np.ndarray, C: np.ndarray, damping: float = 1e-9) -> np.ndarray:
    """Second-order step for min tr(R A R^T) - 2 tr(R C^T) over R (..., 2, 3) with orthonormal rows,
    safeguarded to never increase it.

    R is completed to a rotation Rbar and perturbed as Rbar expm([w]x); with E_k = (Rbar G_k)[:2] for the
    generators G_k, the gradient is 2 tr(E_k (A R^T - C^T)) and the (Gauss-Newton) Hessian 2 tr(E_k A E_l^T).
    Where the rotated R does not lower the objective, one majorise-minimise step is taken instead.
    """
    from scipy.spatial.transform import Rotation

    Rb = complete_rotation(R)
    E = np.einsum("...ij,kjl->...kil", Rb, _GENERATORS)[..., :2, :]  # (..., 3, 2, 3)
    G = np.einsum("...ij,...kj->...ik", A, R) - np.swapaxes(C, -1, -2)  # (..., 3, 2) = A R^T - C^T
    grad = 2.0 * np.einsum("...kij,...ji->...k", E, G)
    H = 2.0 * np.einsum("...kij,...jl,...mil->...km", E, A, E)
    H = H + damping * (np.trace(H, axis1=-2, axis2=-1)[..., None, None] + 1e-300) * np.eye(3)
    w = -np.linalg.solve(H, grad[..., None])[..., 0]
    shape = w.shape[:-1]
    Rn = Rb @ Rotation.from_rotvec(w.reshape(-1, 3)).as_matrix().reshape(shape + (3, 3))
    Rn = Rn[..., :2, :]
    Rmm = stiefel_mm_step(R, A, C)
    better = stiefel_quadratic(Rn, A, C) <= stiefel_quadratic(Rmm, A, C)
    return np.where(better[..., None, None], Rn, Rmm)
