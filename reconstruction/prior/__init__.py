"""The pose prior learned from real motion capture (a Gaussian mixture over joint rotations + joint limits)."""

from reconstruction.prior.gmm import PosePrior, load_default_prior

__all__ = ["PosePrior", "load_default_prior"]
