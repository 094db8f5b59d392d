"""Pose prior over the COCO-17 skeleton's joint rotations (:mod:`reconstruction.body.skeleton17`):
a Gaussian mixture on the 33 axis-angle numbers of the 11 rotating joints (root excluded), plus
per-axis joint-angle limits, both learned from CMU motion capture by
:mod:`reconstruction.prior.train_prior` (weights in ``reconstruction/prior/data/pose_prior.npz``).

Why a GMM and not a VAE (VPoser): the COCO-17 skeleton has only 11 rotating joints (33 numbers, the
bone twists are fixed to zero because COCO-17 keypoints cannot see them), so a 12-component
full-covariance mixture models the pose distribution well, gives an exact, cheap, smooth negative
log-likelihood (a VAE gives only a bound and needs an encoder or a latent parameterisation in the fit),
trains in seconds on the CPU and weighs ~60 KB.

Example::

    prior = load_default_prior()
    e = prior.energy(pose)          # pose (B, 11, 3) axis-angle -> (B,) NLL, 0 at the best pose
    lim = prior.limit_penalty(pose) # (B,) squared excess over the joint limits (rad^2)

Training data credit: "The data used in this project was obtained from mocap.cs.cmu.edu. The database
was created with funding from NSF EIA-0196217."
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from skycap.errors import SkycapError

DEFAULT_PRIOR_PATH = Path(__file__).with_name("data") / "pose_prior.npz"


class PosePrior(torch.nn.Module):
    """GMM prior + joint limits. Buffers: weights (K,), means (K, D), precision Cholesky factors."""

    def __init__(self, weights: np.ndarray, means: np.ndarray, covs: np.ndarray, lo: np.ndarray, hi: np.ndarray):
        super().__init__()
        covs = np.asarray(covs, dtype=np.float64)
        prec = np.linalg.inv(covs)
        L = np.linalg.cholesky(prec)  # prec = L L^T
        logdet_prec = 2 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(-1)
        D = means.shape[1]
        log_norm = np.log(weights) + 0.5 * logdet_prec - 0.5 * D * math.log(2 * math.pi)
        self.register_buffer("means", torch.tensor(means, dtype=torch.float32))
        self.register_buffer("prec_chol", torch.tensor(L, dtype=torch.float32))
        self.register_buffer("log_norm", torch.tensor(log_norm, dtype=torch.float32))
        self.register_buffer("lo", torch.tensor(lo, dtype=torch.float32).reshape(-1))
        self.register_buffer("hi", torch.tensor(hi, dtype=torch.float32).reshape(-1))
        self.best = float(log_norm.max())

    @property
    def dim(self) -> int:
        return int(self.means.shape[1])

    def log_prob(self, pose: torch.Tensor) -> torch.Tensor:
        """log p(pose), pose (B, 11, 3) or (B, 33) -> (B,)."""
        x = pose.reshape(pose.shape[0], -1).to(self.means.dtype)
        d = x[:, None, :] - self.means[None]  # (B, K, D)
        m = torch.einsum("bkd,kde->bke", d, self.prec_chol)
        return torch.logsumexp(self.log_norm[None] - 0.5 * (m * m).sum(-1), dim=-1)

    def energy(self, pose: torch.Tensor) -> torch.Tensor:
        """Negative log-likelihood shifted so that the best component mean scores about 0; (B,)."""
        return self.best - self.log_prob(pose)

    def limit_penalty(self, pose: torch.Tensor) -> torch.Tensor:
        """Sum of squared excess (rad^2) of each axis-angle number over its learned limits; (B,)."""
        x = pose.reshape(pose.shape[0], -1).to(self.lo.dtype)
        return (torch.relu(x - self.hi) ** 2 + torch.relu(self.lo - x) ** 2).sum(-1)

    @classmethod
    def load(cls, path: str | Path = DEFAULT_PRIOR_PATH) -> "PosePrior":
        path = Path(path)
        if not path.is_file():
            raise SkycapError(f"pose prior weights {path} not found; train them with python -m reconstruction.prior.train_prior")
        z = np.load(path)
        return cls(z["weights"], z["means"], z["covs"], z["lo"], z["hi"])


_CACHE: dict = {}


def load_default_prior() -> PosePrior:
    """The committed prior (cached per process)."""
    if "p" not in _CACHE:
        _CACHE["p"] = PosePrior.load()
    return _CACHE["p"]
