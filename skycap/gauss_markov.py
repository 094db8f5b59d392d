"""First-order Gauss-Markov processes (pure numpy): the error model of a drone's own pose estimate.

``x <- x * exp(-dt/tau) + sigma * sqrt(1 - exp(-2 dt/tau)) * N(0, 1)``: stationary std ``sigma``, autocorrelation
``exp(-|lag|/tau)`` (correlation time ``tau``), increments over a short ``dt`` of variance ``2 sigma^2 dt / tau``
(a random walk that stays bounded). One implementation for the simulator's estimator
(:class:`simulator.vehicle.environment.EstimatorErrorModel`, stepped online) and the evaluation harness's pose
errors (:func:`gauss_markov_series`, a whole sampled track at once).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["gauss_markov_step", "gauss_markov_series"]


def gauss_markov_step(x: np.ndarray, dt_s: float, tau_s: float, sigma, rng: np.random.Generator) -> np.ndarray:
    """One exact discrete step of a first-order Gauss-Markov process (shape of ``x`` kept; ``sigma`` broadcasts)."""
    phi = math.exp(-dt_s / tau_s)
    return x * phi + np.asarray(sigma) * math.sqrt(1.0 - phi * phi) * rng.standard_normal(np.shape(x))


def gauss_markov_series(t_s: np.ndarray, tau_s: float, sigma, rng: np.random.Generator, dims: int = 3) -> np.ndarray:
    """The process sampled at the increasing times ``t_s`` (N,) seconds: (N, dims), started in its stationary state
    (first sample ~ N(0, sigma^2)) and stepped exactly between samples (any spacing). ``sigma``: a number or (dims,)
    per axis; ``tau_s`` <= 0 gives white noise of std ``sigma`` (no correlation)."""
    t_s = np.asarray(t_s, dtype=float).reshape(-1)
    if t_s.size and np.any(np.diff(t_s) < 0):
        raise ValueError("gauss_markov_series: t_s must be increasing")
    sig = np.broadcast_to(np.asarray(sigma, dtype=float), (dims,))
    z = rng.standard_normal((len(t_s), dims))
    if tau_s <= 0 or len(t_s) == 0:
        return z * sig
    phi = np.exp(-np.diff(t_s) / tau_s)  # (N-1,)
    out = np.empty((len(t_s), dims))
    out[0] = sig * z[0]
    innov = sig * np.sqrt(1.0 - phi * phi)[:, None] * z[1:]
    for k in range(1, len(t_s)):  # a recursion; N is a few thousand pose samples
        out[k] = out[k - 1] * phi[k - 1] + innov[k - 1]
    return out
