"""Wind, the vehicle's own state-estimate errors, and the battery: small stochastic models over numpy.

All are first-order Gauss-Markov processes where random: ``x <- x * exp(-dt/tau) + sigma *
sqrt(1 - exp(-2 dt/tau)) * N(0, 1)``, whose stationary std is ``sigma`` and whose increments over a
short ``dt`` have variance ``2 sigma^2 dt / tau`` (a random walk that stays bounded): :mod:`skycap.gauss_markov`,
shared with the evaluation harness.
"""

from __future__ import annotations

import math

import numpy as np

from simulator.config import BatteryConfig, EstimatorConfig, WindConfig
from skycap.gauss_markov import gauss_markov_step


class WindModel:
    """Mean wind plus horizontal/vertical Gauss-Markov gusts, uniform over the flight area.

    ``wind_ned_m_s`` (3,) is the velocity of the air (where it blows *to*).
    """

    def __init__(self, cfg: WindConfig, seed: int = 0):
        self.cfg = cfg
        self.rng = np.random.default_rng(seed)
        to = math.radians(cfg.from_direction_deg + 180.0)
        self.mean_ned_m_s = np.array([math.cos(to), math.sin(to), 0.0]) * cfg.mean_speed_m_s
        self.gust_ned_m_s = np.zeros(3)

    def step(self, dt_s: float) -> np.ndarray:
        if self.cfg.gust_std_m_s > 0:
            sigma = np.array([1.0, 1.0, 0.3]) * self.cfg.gust_std_m_s
            self.gust_ned_m_s = gauss_markov_step(
                self.gust_ned_m_s, dt_s, self.cfg.gust_time_constant_s, sigma, self.rng
            )
        return self.wind_ned_m_s

    @property
    def wind_ned_m_s(self) -> np.ndarray:
        return self.mean_ned_m_s + self.gust_ned_m_s


def small_rotation(angles_rad: np.ndarray) -> np.ndarray:
    """Rotation matrix (3,3) of a small rotation vector (3,) (exact Rodrigues)."""
    th = float(np.linalg.norm(angles_rad))
    if th < 1e-12:
        return np.eye(3)
    k = angles_rad / th
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(th) * K + (1.0 - math.cos(th)) * (K @ K)


class EstimatorErrorModel:
    """Errors of the autopilot's own estimate (EKF output) relative to the truth.

    * position: slowly drifting bias (Gauss-Markov, std ``pos_bias_std_*``, correlation time
      ``pos_bias_time_constant_s``) + small white noise;
    * velocity: white noise;
    * attitude: a rotation error with per-axis std ``att_noise_std_deg`` (Gauss-Markov,
      ``att_noise_time_constant_s``): ``R_est = R_true @ small_rotation(err)``;
    * :meth:`jump`: a sudden step of the position bias (a GPS jump, e.g. a multipath or satellite-set
      change; fault tests). It stays in the bias, which then relaxes with its correlation time.
    """

    def __init__(self, cfg: EstimatorConfig, seed: int):
        self.cfg = cfg
        self.rng = np.random.default_rng(seed)
        self.pos_sigma = np.array([cfg.pos_bias_std_xy_m, cfg.pos_bias_std_xy_m, cfg.pos_bias_std_z_m])
        # start from the stationary distribution (the EKF has converged to *some* bias)
        self.pos_bias_m = self.pos_sigma * self.rng.standard_normal(3)
        self.att_sigma_rad = math.radians(cfg.att_noise_std_deg)
        self.att_err_rad = self.att_sigma_rad * self.rng.standard_normal(3)
        self.pos_noise_m = np.zeros(3)
        self.vel_noise_m_s = np.zeros(3)

    def jump(self, offset_ned_m) -> None:
        """Add ``offset_ned_m`` (3,) to the position bias now (reported position jumps by it)."""
        off = np.asarray(offset_ned_m, dtype=float).reshape(3)
        if not np.all(np.isfinite(off)):
            raise ValueError(f"GPS jump offset must be 3 finite metres (north, east, down), got {offset_ned_m!r}")
        self.pos_bias_m = self.pos_bias_m + off

    def step(self, dt_s: float) -> None:
        c = self.cfg
        if c.pos_bias_time_constant_s > 0:
            self.pos_bias_m = gauss_markov_step(
                self.pos_bias_m, dt_s, c.pos_bias_time_constant_s, self.pos_sigma, self.rng
            )
        if c.att_noise_time_constant_s > 0:
            self.att_err_rad = gauss_markov_step(
                self.att_err_rad, dt_s, c.att_noise_time_constant_s, self.att_sigma_rad, self.rng
            )
        noise = self.rng.standard_normal(6)
        self.pos_noise_m = c.pos_noise_std_m * noise[:3]
        self.vel_noise_m_s = c.vel_noise_std_m_s * noise[3:]

    def estimate(self, position_ned_m: np.ndarray, velocity_ned_m_s: np.ndarray, R_world_body: np.ndarray):
        """(position (3,), velocity (3,), R_world_body (3,3)) as the autopilot believes them."""
        return (
            position_ned_m + self.pos_bias_m + self.pos_noise_m,
            velocity_ned_m_s + self.vel_noise_m_s,
            R_world_body @ small_rotation(self.att_err_rad),
        )


class Battery:
    """Linear-drain battery; ``remaining_pct`` drops faster with thrust (scaled by thrust/g)."""

    def __init__(self, cfg: BatteryConfig):
        self.cfg = cfg
        self.remaining_pct = float(cfg.start_percent)
        self.consumed_mah = (100.0 - self.remaining_pct) / 100.0 * cfg.capacity_mah
        self.current_a = 0.0

    def step(self, dt_s: float, armed: bool, thrust_ratio: float) -> None:
        c = self.cfg
        rate = c.hover_drain_pct_per_min * max(thrust_ratio, 0.3) if armed else c.idle_drain_pct_per_min
        d_pct = rate / 60.0 * dt_s
        self.remaining_pct = max(0.0, self.remaining_pct - d_pct)
        self.current_a = rate / 100.0 * c.capacity_mah / 1000.0 * 60.0  # %/min -> A
        self.consumed_mah = (100.0 - self.remaining_pct) / 100.0 * c.capacity_mah

    @property
    def voltage_v(self) -> float:
        """Pack voltage: 3.5 V/cell empty .. 4.2 V/cell full, linear."""
        return self.cfg.cells * (3.5 + 0.7 * self.remaining_pct / 100.0)
