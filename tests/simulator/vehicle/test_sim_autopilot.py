"""The simulated PX4 commander/autopilot without I/O: modes, arming, failsafes, frames, params."""

import math

import numpy as np
import pytest
from sim_vehicle_helpers import fast_forward

from simulator.config import SimConfig
from simulator.vehicle import autopilot as ap
from simulator.vehicle.autopilot import SimVehicle
from simulator.vehicle.controller import TrajectorySetpoint
from simulator.vehicle.px4_modes import FlightMode, MainMode


def airborne(index=0, cfg=None, alt=None) -> SimVehicle:
    cfg = cfg or SimConfig()
    v = SimVehicle(index, cfg.validate())
    fast_forward(v, cfg.estimator.gps_lock_delay_s + 0.1)
    assert v.cmd_arm(True) == ap.ACCEPTED
    assert v.cmd_takeoff() == ap.ACCEPTED
    fast_forward(v, 8.0)
    assert v.mode == FlightMode.HOLD and not v.landed
    return v


def stream(sp_local):
    def each(v):
        v.set_offboard_setpoint(TrajectorySetpoint(position_ned_m=np.array(sp_local, float), yaw_rad=0.0))

    return each


def test_arming_needs_gps_then_takeoff_to_mis_takeoff_alt_and_hold():
    cfg = SimConfig(takeoff_alt_m=4.0)
    v = SimVehicle(0, cfg.validate())
    assert v.cmd_arm(True) == ap.DENIED  # no GPS fix yet
    assert v.cmd_takeoff() == ap.TEMPORARILY_REJECTED  # disarmed
    fast_forward(v, 1.2)
    assert v.gps_ok and v.home_ned_m is not None
    assert v.cmd_arm(True) == ap.ACCEPTED and v.armed
    assert v.cmd_takeoff() == ap.ACCEPTED and v.mode == FlightMode.TAKEOFF
    states = set()
    fast_forward(v, 8.0, each_step=lambda v: states.add(v.landed_state))
    assert {ap.LANDED_ON_GROUND, ap.LANDED_TAKEOFF, ap.LANDED_IN_AIR} <= states
    assert v.mode == FlightMode.HOLD
    assert v.home_ned_m[2] - v.est_position_ned_m[2] == pytest.approx(4.0, abs=0.2)  # above home (estimate)
    assert v.cmd_arm(False) == ap.DENIED  # no disarm in the air ...
    assert v.cmd_arm(False, force=True) == ap.ACCEPTED  # ... unless forced (kill)


def test_offboard_refused_without_setpoints_then_dropped_to_hold_when_they_stop():
    v = airborne()
    assert v.cmd_set_mode(1, MainMode.OFFBOARD, 0) == ap.TEMPORARILY_REJECTED
    assert v.mode == FlightMode.HOLD
    fast_forward(v, 0.3, each_step=stream([0.0, 0.0, -5.0]))
    assert v.cmd_set_mode(1, MainMode.OFFBOARD, 0) == ap.ACCEPTED and v.mode == FlightMode.OFFBOARD
    fast_forward(v, 3.0, each_step=stream([2.0, 0.0, -5.0]))
    assert v.mode == FlightMode.OFFBOARD
    t_last = v.t_s
    while v.mode == FlightMode.OFFBOARD and v.t_s < t_last + 2.0:
        fast_forward(v, 0.01)
    assert v.mode == FlightMode.HOLD
    assert 0.49 <= v.t_s - t_last <= 0.56  # COM_OF_LOSS_T = 0.5 s
    assert any("no offboard signal" in t for _, t in v.status_texts)
    p = v.est_position_ned_m.copy()
    fast_forward(v, 3.0)
    assert np.linalg.norm(v.est_position_ned_m[:2] - p[:2]) < 1.0  # holds about where it was


def test_offboard_loss_action_land():
    cfg = SimConfig()
    cfg.failsafe.offboard_loss_action = "land"
    v = airborne(cfg=cfg)
    fast_forward(v, 0.2, each_step=stream([0.0, 0.0, -5.0]))
    assert v.cmd_set_mode(1, MainMode.OFFBOARD, 0) == ap.ACCEPTED
    fast_forward(v, 1.0)
    assert v.mode == FlightMode.LAND


def test_offboard_setpoints_are_in_the_vehicles_local_frame():
    cfg = SimConfig()
    cfg.vehicles.count = 2
    cfg.estimator.pos_bias_std_xy_m = cfg.estimator.pos_bias_std_z_m = 0.0
    v = airborne(index=1, cfg=cfg)  # spawned 3 m east of the origin
    assert np.allclose(v.spawn_ned_m, [0.0, 3.0, 0.0])
    fast_forward(v, 0.2, each_step=stream([5.0, 0.0, -3.0]))
    v.cmd_set_mode(1, MainMode.OFFBOARD, 0)
    fast_forward(v, 8.0, each_step=stream([5.0, 0.0, -3.0]))
    np.testing.assert_allclose(v.truth.position_ned_m, [5.0, 3.0, -3.0], atol=0.15)
    np.testing.assert_allclose(v.est_local_position_ned_m, [5.0, 0.0, -3.0], atol=0.15)


def test_land_then_auto_disarm():
    v = airborne()
    assert v.cmd_land() == ap.ACCEPTED
    fast_forward(v, 0.5)
    assert v.landed_state == ap.LANDED_LANDING
    t0 = v.t_s
    while not v.landed:
        fast_forward(v, 0.05)
    assert v.t_s - t0 < 2.5 / 0.7 + 2.0  # ~2.5 m at MPC_LAND_SPEED 0.7 m/s
    assert v.armed
    fast_forward(v, 2.2)
    assert not v.armed and any("auto disarm" in t for _, t in v.status_texts)


def test_return_to_launch_climbs_returns_and_lands_at_home():
    cfg = SimConfig(rtl_return_alt_m=6.0)
    v = airborne(cfg=cfg)
    home = v.home_ned_m.copy()
    fast_forward(v, 0.2, each_step=stream([15.0, 5.0, -3.0]))
    v.cmd_set_mode(1, MainMode.OFFBOARD, 0)
    fast_forward(v, 8.0, each_step=stream([15.0, 5.0, -3.0]))
    assert v.cmd_return() == ap.ACCEPTED and v.mode == FlightMode.RETURN
    min_d = 0.0
    for _ in range(300):
        fast_forward(v, 0.1)
        min_d = min(min_d, v.est_position_ned_m[2] - home[2])
        if v.landed:
            break
    assert v.landed
    assert min_d == pytest.approx(-6.0, abs=0.4)  # climbed to RTL_RETURN_ALT first
    assert np.linalg.norm(v.est_position_ned_m[:2] - home[:2]) < 0.6


def test_low_battery_denies_arming_and_triggers_return_in_flight():
    cfg = SimConfig()
    cfg.battery.start_percent = 5.0
    v = SimVehicle(0, cfg.validate())
    fast_forward(v, 1.5)
    assert v.cmd_arm(True) == ap.DENIED
    cfg = SimConfig()
    cfg.battery.start_percent = 9.0
    cfg.battery.hover_drain_pct_per_min = 12.0  # forced: 0.2 %/s at hover
    v = airborne(cfg=cfg)
    assert v.battery.remaining_pct > 7.0
    fast_forward(v, 6.0)
    assert v.mode in (FlightMode.RETURN,) and any("battery critical" in t for _, t in v.status_texts)
    assert any("Low battery" in t for _, t in v.status_texts)


def test_preflight_auto_disarm():
    v = SimVehicle(0, SimConfig().validate())
    fast_forward(v, 1.5)
    v.cmd_arm(True)
    fast_forward(v, 9.0)
    assert v.armed
    fast_forward(v, 1.5)
    assert not v.armed


def test_params_change_the_flight_envelope():
    v = airborne()
    assert v.params.set("MPC_XY_VEL_MAX", 3.0) is not None
    assert v.params.set("NO_SUCH_PARAM", 1.0) is None
    fast_forward(v, 0.2, each_step=stream([40.0, 0.0, -3.0]))
    v.cmd_set_mode(1, MainMode.OFFBOARD, 0)
    speeds = []
    fast_forward(
        v,
        8.0,
        each_step=lambda v: (stream([40.0, 0.0, -3.0])(v), speeds.append(math.hypot(*v.truth.velocity_ned_m_s[:2]))),
    )
    assert 2.8 < max(speeds) < 3.2


def test_manual_modes_and_mission_are_rejected_without_rc_or_mission():
    v = airborne()
    assert v.cmd_set_mode(1, MainMode.POSCTL, 0) == ap.TEMPORARILY_REJECTED
    assert v.cmd_set_mode(1, MainMode.AUTO, 4) == ap.TEMPORARILY_REJECTED  # mission
    assert v.cmd_set_mode(0, MainMode.AUTO, 3) == ap.UNSUPPORTED  # no custom-mode flag
    assert v.mode == FlightMode.HOLD


def test_takeoff_altitude_from_param7_amsl_or_mis_takeoff_alt():
    cfg = SimConfig()
    cfg.estimator.pos_bias_std_xy_m = cfg.estimator.pos_bias_std_z_m = 0.0
    v = SimVehicle(0, cfg.validate())
    fast_forward(v, 1.2)
    v.cmd_arm(True)
    assert v.cmd_takeoff(cfg.origin.alt_m + 6.0) == ap.ACCEPTED
    fast_forward(v, 7.0)
    assert -v.truth.position_ned_m[2] == pytest.approx(6.0, abs=0.2)
    v2 = SimVehicle(0, cfg)
    fast_forward(v2, 1.2)
    v2.cmd_arm(True)
    assert v2.cmd_takeoff(0.0) == ap.ACCEPTED  # 0 m AMSL: below home -> MIS_TAKEOFF_ALT
    fast_forward(v2, 6.0)
    assert -v2.truth.position_ned_m[2] == pytest.approx(cfg.takeoff_alt_m, abs=0.2)
