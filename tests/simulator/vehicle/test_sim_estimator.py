"""Estimator error model: slowly drifting position bias at the configured rate, ~1 degree attitude noise."""

import math

import numpy as np
import pytest

from simulator.config import BatteryConfig, EstimatorConfig
from simulator.vehicle.environment import Battery, EstimatorErrorModel, small_rotation


def test_position_bias_is_a_bounded_random_walk_with_the_configured_rate():
    cfg = EstimatorConfig(pos_bias_std_xy_m=1.0, pos_bias_std_z_m=0.5, pos_bias_time_constant_s=60.0)
    models = [EstimatorErrorModel(cfg, seed=s) for s in range(400)]
    dt, steps = 0.1, 100  # 10 s
    start = np.array([m.pos_bias_m for m in models])
    for _ in range(steps):
        for m in models:
            m.step(dt)
    end = np.array([m.pos_bias_m for m in models])
    # stationary spread = configured std
    assert start[:, 0].std() == pytest.approx(1.0, rel=0.12)
    assert end[:, 2].std() == pytest.approx(0.5, rel=0.12)
    # drift over T: var = 2 sigma^2 (1 - exp(-T/tau)) -> ~0.41 m per 10 s horizontally (slow: metres per minute)
    drift = end - start
    expected = math.sqrt(2 * 1.0**2 * (1 - math.exp(-10.0 / 60.0)))
    assert drift[:, 0].std() == pytest.approx(expected, rel=0.12)
    assert drift[:, 1].std() == pytest.approx(expected, rel=0.12)


def test_bias_time_constant_changes_the_drift_rate():
    fast = EstimatorConfig(pos_bias_time_constant_s=5.0)
    slow = EstimatorConfig(pos_bias_time_constant_s=500.0)

    def drift(cfg):
        ms = [EstimatorErrorModel(cfg, seed=s) for s in range(300)]
        a = np.array([m.pos_bias_m[0] for m in ms])
        for _ in range(20):
            for m in ms:
                m.step(0.1)
        return (np.array([m.pos_bias_m[0] for m in ms]) - a).std()

    assert drift(fast) > 3 * drift(slow)


def test_attitude_noise_is_about_one_degree():
    cfg = EstimatorConfig(att_noise_std_deg=1.0, att_noise_time_constant_s=1.0)
    m = EstimatorErrorModel(cfg, seed=1)
    R_true = small_rotation(np.array([0.1, -0.2, 1.0]))
    angles = []
    for _ in range(30000):
        m.step(0.02)
        _, _, R_est = m.estimate(np.zeros(3), np.zeros(3), R_true)
        dR = R_true.T @ R_est
        angles.append(math.degrees(math.acos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
        per_axis = m.att_err_rad
    angles = np.array(angles)
    # total angle of a 3-axis error with 1 deg per axis: RMS = sqrt(3) deg
    assert math.sqrt(np.mean(angles**2)) == pytest.approx(math.sqrt(3.0), rel=0.15)
    assert np.degrees(np.abs(per_axis)).max() < 6.0


def test_estimate_keeps_the_truth_apart():
    m = EstimatorErrorModel(EstimatorConfig(), seed=2)
    p, v, R = np.array([1.0, 2.0, -3.0]), np.array([0.5, 0.0, 0.0]), np.eye(3)
    m.step(0.01)
    pe, ve, Re = m.estimate(p, v, R)
    assert not np.allclose(pe, p) and np.linalg.norm(pe - p) < 6.0
    assert np.allclose(p, [1.0, 2.0, -3.0])  # inputs untouched


def test_battery_drains_when_armed_and_can_start_low():
    b = Battery(BatteryConfig(start_percent=50.0, hover_drain_pct_per_min=6.0))
    for _ in range(600):
        b.step(0.1, armed=True, thrust_ratio=1.0)
    assert b.remaining_pct == pytest.approx(44.0, abs=0.01)
    assert 4 * 3.5 < b.voltage_v < 4 * 4.2
    idle = Battery(BatteryConfig())
    idle.step(60.0, armed=False, thrust_ratio=0.0)
    assert idle.remaining_pct > 99.9
