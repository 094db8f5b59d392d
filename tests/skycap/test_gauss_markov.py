"""skycap.gauss_markov: the stationary std and correlation time of the one Gauss-Markov implementation."""

import numpy as np
import pytest

from skycap.gauss_markov import gauss_markov_series, gauss_markov_step


def _autocorr(x: np.ndarray, lag: int) -> float:
    x = x - x.mean()
    return float(np.dot(x[:-lag], x[lag:]) / np.dot(x, x))


def test_series_has_the_stationary_std_and_the_correlation_time():
    rng = np.random.default_rng(0)
    dt, tau, sigma = 0.1, 2.0, np.array([0.5, 0.5, 2.0])
    x = gauss_markov_series(np.arange(200_000) * dt, tau, sigma, rng)
    np.testing.assert_allclose(x.std(axis=0), sigma, rtol=0.04)
    for lag in (1, 20):  # autocorrelation exp(-lag dt / tau): 0.951 and 1/e
        assert _autocorr(x[:, 0], lag) == pytest.approx(np.exp(-lag * dt / tau), abs=0.04)


def test_series_starts_stationary_and_steps_exactly_over_uneven_times():
    rng = np.random.default_rng(1)
    # many independent short series: the first sample already has the stationary std; a 1-tau gap correlates 1/e
    first, after = [], []
    for _ in range(4000):
        x = gauss_markov_series(np.array([0.0, 0.05, 1.0]), 1.0, 3.0, rng, dims=1)
        first.append(x[0, 0])
        after.append(x[2, 0])
    first, after = np.array(first), np.array(after)
    assert first.std() == pytest.approx(3.0, rel=0.05)
    assert after.std() == pytest.approx(3.0, rel=0.05)
    assert np.corrcoef(first, after)[0, 1] == pytest.approx(np.exp(-1.0), abs=0.05)


def test_zero_time_constant_is_white_noise_and_times_must_increase():
    x = gauss_markov_series(np.arange(20_000) * 0.1, 0.0, 1.5, np.random.default_rng(2))
    assert x.std() == pytest.approx(1.5, rel=0.03) and abs(_autocorr(x[:, 1], 1)) < 0.03
    with pytest.raises(ValueError, match="increasing"):
        gauss_markov_series(np.array([0.0, 1.0, 0.5]), 1.0, 1.0, np.random.default_rng(0))


def test_step_keeps_the_stationary_std():
    """The simulator's online step (simulator.vehicle.environment) is the same process."""
    rng = np.random.default_rng(3)
    x, xs = np.zeros(3), []
    for _ in range(50_000):
        x = gauss_markov_step(x, 0.02, 1.0, 0.7, rng)
        xs.append(x)
    assert np.array(xs)[5000:].std() == pytest.approx(0.7, rel=0.08)
    from simulator.vehicle import environment

    assert environment.gauss_markov_step is gauss_markov_step
