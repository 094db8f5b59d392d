"""Multirotor dynamics + PX4-like position controller, stepped faster than real time (no I/O)."""

import math

import numpy as np
import pytest

from simulator.config import WindConfig
from simulator.vehicle.controller import ControllerLimits, PositionController, TrajectorySetpoint
from simulator.vehicle.dynamics import GRAVITY_M_S2, DynamicsLimits, MultirotorDynamics
from simulator.vehicle.environment import WindModel

DT = 0.01


def make(pos=(0.0, 0.0, -5.0), yaw=0.0):
    dyn = MultirotorDynamics(DynamicsLimits(max_tilt_rad=math.radians(35.0) * 1.05), position_ned_m=pos, yaw_rad=yaw)
    dyn.state.on_ground = pos[2] >= 0
    dyn.state.thrust_m_s2 = GRAVITY_M_S2 if pos[2] < 0 else 0.0
    return dyn, PositionController(ControllerLimits.from_config())


def fly(dyn, ctrl, sp, seconds, wind=None, log=None):
    wind = np.zeros(3) if wind is None else wind
    for _ in range(int(seconds / DT)):
        s = dyn.state
        z, thrust, yaw_rate = ctrl.update(DT, sp, s.position_ned_m, s.velocity_ned_m_s, s.yaw_rad, s.on_ground)
        dyn.step(DT, z, thrust, yaw_rate, wind)
        if log is not None:
            log.append(
                (
                    s.position_ned_m.copy(),
                    s.velocity_ned_m_s.copy(),
                    s.accel_ned_m_s2.copy(),
                    s.R_world_body.copy(),
                    s.yaw_rad,
                )
            )


def test_limits_on_a_long_leg_climb_descent_and_yaw():
    # a far position setpoint straight to the controller (PX4 offboard: no trajectory smoothing): the velocity
    # *setpoint* is held to MPC_XY_VEL_MAX / MPC_Z_VEL_MAX_UP / _DN; the velocity loop may overshoot it briefly
    dyn, ctrl = make()
    log, vsp = [], []
    orig_update = ctrl.update

    def update(*a, **k):
        out = orig_update(*a, **k)
        vsp.append(ctrl.velocity_setpoint_ned_m_s.copy())
        return out

    ctrl.update = update
    fly(dyn, ctrl, TrajectorySetpoint(position_ned_m=np.array([250.0, 0.0, -40.0]), yaw_rad=math.pi), 40.0, log=log)
    fly(dyn, ctrl, TrajectorySetpoint(position_ned_m=np.array([250.0, 0.0, -5.0]), yaw_rad=math.pi), 30.0, log=log)
    pos, vel, acc, R, yaw = (np.array([e[i] for e in log]) for i in range(5))
    vsp = np.array(vsp)
    assert np.hypot(vsp[:, 0], vsp[:, 1]).max() == pytest.approx(12.0)
    assert (-vsp[:, 2]).max() == pytest.approx(3.0) and vsp[:, 2].max() == pytest.approx(1.5)
    speed_xy = np.hypot(vel[:, 0], vel[:, 1])
    tilt_deg = np.degrees(np.arccos(np.clip(R[:, 2, 2], -1, 1)))
    yaw_rate = np.abs(np.diff(np.unwrap(yaw))) / DT
    assert 11.0 < speed_xy.max() <= 12.0 * 1.05  # the horizontal limit is reached, hardly exceeded
    assert 2.8 < (-vel[:, 2]).max() <= 3.0 * 1.2  # climb limit (+ the velocity loop's overshoot)
    assert 1.3 < vel[:, 2].max() <= 1.5 * 1.2  # descent limit
    assert tilt_deg.max() <= 35.0 * 1.05 + 0.1
    assert np.degrees(yaw_rate.max()) <= 60.0 * 1.02
    assert np.linalg.norm(pos[-1] - [250.0, 0.0, -5.0]) < 0.2


def test_reaches_position_setpoint_without_big_overshoot():
    dyn, ctrl = make()
    target = np.array([20.0, -10.0, -8.0])
    log = []
    fly(dyn, ctrl, TrajectorySetpoint(position_ned_m=target, yaw_rad=0.7), 15.0, log=log)
    pos = np.array([e[0] for e in log])
    assert np.linalg.norm(pos[-1] - target) < 0.1
    along = (pos - pos[0]) @ (target - pos[0]) / np.linalg.norm(target - pos[0])
    assert along.max() - np.linalg.norm(target - pos[0]) < 0.8  # overshoot along the leg
    assert dyn.state.yaw_rad == pytest.approx(0.7, abs=0.02)


def test_tracks_velocity_setpoint():
    dyn, ctrl = make()
    fly(dyn, ctrl, TrajectorySetpoint(velocity_ned_m_s=np.array([3.0, -1.0, -0.5])), 6.0)
    np.testing.assert_allclose(dyn.state.velocity_ned_m_s, [3.0, -1.0, -0.5], atol=0.05)


def test_wind_pushes_an_uncontrolled_vehicle_downwind_and_the_controller_leans_into_it():
    wind_cfg = WindConfig(mean_speed_m_s=6.0, from_direction_deg=270.0)  # from the west: blows east
    wind = WindModel(wind_cfg).step(DT)
    np.testing.assert_allclose(wind, [0.0, 6.0, 0.0], atol=1e-9)
    # level hover thrust, no position control: drifts east
    dyn, _ = make()
    for _ in range(int(5.0 / DT)):
        dyn.step(DT, np.array([0.0, 0.0, 1.0]), GRAVITY_M_S2, 0.0, wind)
    assert dyn.state.position_ned_m[1] > 10.0 and abs(dyn.state.position_ned_m[0]) < 1e-6
    assert dyn.state.velocity_ned_m_s[1] == pytest.approx(6.0 * (1 - math.exp(-0.25 * 5.0)), rel=0.05)
    # position control: holds the point, tilted west (into the wind)
    dyn, ctrl = make()
    log = []
    fly(dyn, ctrl, TrajectorySetpoint(position_ned_m=np.array([0.0, 0.0, -5.0])), 20.0, wind=wind, log=log)
    max_drift = max(np.linalg.norm(e[0] - [0, 0, -5]) for e in log)
    assert 0.05 < max_drift < 3.0
    assert np.linalg.norm(dyn.state.position_ned_m - [0, 0, -5]) < 0.1
    assert dyn.state.R_world_body[1, 2] > 0.1  # thrust (= -body z) has a westward part: leans into the wind


def test_gusts_have_the_configured_spread():
    wm = WindModel(WindConfig(mean_speed_m_s=0.0, gust_std_m_s=2.0, gust_time_constant_s=1.0), seed=3)
    samples = np.array([wm.step(0.05).copy() for _ in range(40000)])
    assert samples[:, 0].std() == pytest.approx(2.0, rel=0.1)
    assert samples[:, 2].std() == pytest.approx(0.6, rel=0.1)


def test_ground_contact():
    dyn, ctrl = make(pos=(0.0, 0.0, 0.0))
    for _ in range(100):  # disarmed: stays put on the ground, level
        dyn.step(DT, np.array([0.3, 0.0, 0.95]), 0.0, 1.0, np.array([5.0, 0.0, 0.0]), motors_on=False)
    assert (
        dyn.state.on_ground
        and np.allclose(dyn.state.position_ned_m, 0.0)
        and dyn.state.R_world_body[2, 2] == pytest.approx(1.0)
    )
    fly(dyn, ctrl, TrajectorySetpoint(position_ned_m=np.array([0.0, 0.0, -2.0])), 4.0)  # takes off
    assert not dyn.state.on_ground and dyn.state.position_ned_m[2] == pytest.approx(-2.0, abs=0.05)
    for _ in range(int(3.0 / DT)):  # motors cut: falls and rests on the ground, not below it
        dyn.step(DT, np.array([0.0, 0.0, 1.0]), 0.0, 0.0, np.zeros(3), motors_on=False)
    assert dyn.state.on_ground and dyn.state.position_ned_m[2] == 0.0


def test_attitude_from_thrust_axis_and_yaw_is_a_rotation_with_that_heading():
    from scipy.spatial.transform import Rotation

    from simulator.vehicle.dynamics import R_from_body_z_and_yaw

    rng = np.random.default_rng(0)
    for _ in range(100):
        R = Rotation.from_euler("ZYX", [rng.uniform(-3, 3), rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6)]).as_matrix()
        yaw = math.atan2(R[1, 0], R[0, 0])
        R2 = R_from_body_z_and_yaw(R[:, 2], yaw)
        np.testing.assert_allclose(R2.T @ R2, np.eye(3), atol=1e-12)
        assert np.linalg.det(R2) == pytest.approx(1.0)
        np.testing.assert_allclose(R2[:, 2], R[:, 2], atol=1e-12)
        np.testing.assert_allclose(R2, R, atol=1e-9)  # same tilt + same heading = same attitude (ZYX)


def test_acceleration_only_setpoint_is_flown_open_loop():
    dyn, ctrl = make()
    fly(dyn, ctrl, TrajectorySetpoint(accel_ned_m_s2=np.array([1.0, 0.0, 0.0])), 3.0)
    v = dyn.state.velocity_ned_m_s
    # 1 m/s^2 forward against linear drag 0.25/s: v = 4 (1 - exp(-0.25 t)) ~ 2.1 m/s after 3 s
    assert v[0] == pytest.approx(4.0 * (1 - math.exp(-0.75)), abs=0.2) and abs(v[2]) < 0.05
