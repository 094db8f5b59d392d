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
    heights_at_hold = []

    def each(v):
        states.add(v.landed_state)
        if v.mode == FlightMode.HOLD and not heights_at_hold:
            heights_at_hold.append(v.home_ned_m[2] - v.est_position_ned_m[2])

    fast_forward(v, 8.0, each_step=each)
    assert {ap.LANDED_ON_GROUND, ap.LANDED_TAKEOFF, ap.LANDED_IN_AIR} <= states
    assert v.mode == FlightMode.HOLD
    # PX4: takeoff complete NAV_MC_ALT_RAD (0.8 m) below the takeoff altitude; Hold then climbs the rest
    assert heights_at_hold[0] == pytest.approx(4.0 - 0.8, abs=0.1)
    assert v.home_ned_m[2] - v.est_position_ned_m[2] == pytest.approx(4.0, abs=0.2)  # above home (estimate)
    assert v.cmd_arm(False) == ap.DENIED  # no disarm in the air ...
    assert v.cmd_arm(False, force=True) == ap.ACCEPTED  # ... unless forced (kill)


def test_takeoff_defaults_to_2_5_m_and_is_in_air_during_the_climb():
    v = SimVehicle(0, SimConfig().validate())
    assert v.params["MIS_TAKEOFF_ALT"] == 2.5
    fast_forward(v, 1.2)
    v.cmd_arm(True)
    v.cmd_takeoff()
    in_air_in_takeoff = []
    fast_forward(v, 6.0, each_step=lambda v: in_air_in_takeoff.append(
        v.mode == FlightMode.TAKEOFF and v.landed_state == ap.LANDED_IN_AIR))
    assert any(in_air_in_takeoff)  # MAVSDK in_air turns true while PX4 is still in Takeoff
    assert v.mode == FlightMode.HOLD
    assert v.home_ned_m[2] - v.est_position_ned_m[2] == pytest.approx(2.5, abs=0.2)


def test_offboard_requested_as_the_takeoff_completes_is_overridden_by_its_hold():
    v = SimVehicle(0, SimConfig().validate())
    fast_forward(v, 1.2)
    v.cmd_arm(True)
    v.cmd_takeoff()
    sp = stream([0.0, 0.0, -2.5])
    # climb until just below the takeoff's acceptance height (PX4's navigator completes it a moment later)
    accept_h = 2.5 - v.params["NAV_MC_ALT_RAD"]
    while v.home_ned_m[2] - v.est_position_ned_m[2] < accept_h - 0.05:
        fast_forward(v, 0.01, each_step=sp)
    assert v.mode == FlightMode.TAKEOFF
    assert v.cmd_set_mode(1, MainMode.OFFBOARD, 0) == ap.ACCEPTED  # ACKed ...
    fast_forward(v, 0.05, each_step=sp)
    assert v.mode == FlightMode.HOLD  # ... but the takeoff's Hold wins, as on PX4
    assert v.cmd_set_mode(1, MainMode.OFFBOARD, 0) == ap.ACCEPTED  # asked again: stays
    fast_forward(v, 1.0, each_step=sp)
    assert v.mode == FlightMode.OFFBOARD


def test_offboard_requested_early_in_the_climb_is_kept():
    v = SimVehicle(0, SimConfig().validate())
    fast_forward(v, 1.2)
    v.cmd_arm(True)
    v.cmd_takeoff()
    sp = stream([0.0, 0.0, -2.5])
    fast_forward(v, 1.0, each_step=sp)
    assert v.mode == FlightMode.TAKEOFF
    assert v.cmd_set_mode(1, MainMode.OFFBOARD, 0) == ap.ACCEPTED
    fast_forward(v, 5.0, each_step=sp)
    assert v.mode == FlightMode.OFFBOARD


def offboard_at(v, sp_local, seconds: float = 3.0):
    """Stream ``sp_local``, switch to Offboard and fly it for ``seconds``."""
    fast_forward(v, 0.3, each_step=stream(sp_local))
    assert v.cmd_set_mode(1, MainMode.OFFBOARD, 0) == ap.ACCEPTED and v.mode == FlightMode.OFFBOARD
    fast_forward(v, seconds, each_step=stream(sp_local))


def until_mode_leaves(v, mode, limit_s: float = 3.0) -> float:
    """Step until the mode is no longer ``mode``; seconds it took."""
    t0 = v.t_s
    while v.mode == mode and v.t_s < t0 + limit_s:
        fast_forward(v, 0.01)
    return v.t_s - t0


def test_offboard_refused_without_setpoints_then_returns_on_loss_and_resumes_offboard():
    # PX4 defaults: COM_OF_LOSS_T 1 s, COM_OBL_RC_ACT 0 (Position mode; no RC -> Return)
    v = airborne()
    assert v.params["COM_OF_LOSS_T"] == 1.0 and v.params["COM_OBL_RC_ACT"] == 0
    assert v.cmd_set_mode(1, MainMode.OFFBOARD, 0) == ap.TEMPORARILY_REJECTED
    assert v.mode == FlightMode.HOLD
    offboard_at(v, [2.0, 0.0, -5.0])
    assert v.mode == FlightMode.OFFBOARD
    assert 0.99 <= until_mode_leaves(v, FlightMode.OFFBOARD) <= 1.06
    assert v.mode == FlightMode.RETURN
    assert any("no offboard signal, returning" in t for _, t in v.status_texts)
    fast_forward(v, 2.0)
    assert v.mode == FlightMode.RETURN
    # setpoints resume: back to Offboard by itself (PX4's failsafe clears, the intended mode was Offboard)
    fast_forward(v, 0.05, each_step=stream([2.0, 0.0, -5.0]))
    assert v.mode == FlightMode.OFFBOARD
    assert any("back to Offboard" in t for _, t in v.status_texts)


@pytest.mark.parametrize("act, mode", [(3, FlightMode.RETURN), (4, FlightMode.LAND), (5, FlightMode.HOLD)])
def test_offboard_loss_action_follows_com_obl_rc_act(act, mode):
    v = airborne()
    assert v.params.set("COM_OBL_RC_ACT", act) is not None
    offboard_at(v, [2.0, 0.0, -5.0])
    until_mode_leaves(v, FlightMode.OFFBOARD)
    assert v.mode == mode
    if mode == FlightMode.HOLD:
        p = v.est_position_ned_m.copy()
        fast_forward(v, 3.0)
        assert np.linalg.norm(v.est_position_ned_m[:2] - p[:2]) < 1.0  # holds about where it was
    # a commanded mode change ends the failsafe's claim: resuming setpoints no longer switches back
    assert v.cmd_hold() == ap.ACCEPTED
    fast_forward(v, 0.2, each_step=stream([2.0, 0.0, -5.0]))
    assert v.mode == FlightMode.HOLD


def test_offboard_loss_action_from_config_and_disarm_action():
    cfg = SimConfig()
    cfg.failsafe.offboard_loss_action = "land"
    v = airborne(cfg=cfg)
    assert v.params["COM_OBL_RC_ACT"] == 4
    offboard_at(v, [0.0, 0.0, -5.0], 0.5)
    fast_forward(v, 1.2)
    assert v.mode == FlightMode.LAND
    v = airborne()
    v.params.set("COM_OBL_RC_ACT", 7)
    offboard_at(v, [0.0, 0.0, -5.0], 0.5)
    fast_forward(v, 1.2)
    assert not v.armed  # motors off where it was


def test_landed_from_offboard_stays_offboard_and_is_not_armable_until_a_mode_change():
    # PX4 (measured): after landing from Offboard it disarms, keeps reporting Offboard, and without a live
    # setpoint stream it is not armable until another mode is set; with setpoints streaming it arms in Offboard
    v = airborne()
    home = v.home_ned_m.copy()
    down = lambda v: v.set_offboard_setpoint(TrajectorySetpoint(velocity_ned_m_s=np.array([0.0, 0.0, 0.7])))  # noqa: E731
    fast_forward(v, 0.2, each_step=down)
    assert v.cmd_set_mode(1, MainMode.OFFBOARD, 0) == ap.ACCEPTED
    fast_forward(v, 12.0, each_step=down)
    assert v.landed and not v.armed  # COM_DISARM_LAND 2 s after touchdown
    assert v.mode == FlightMode.OFFBOARD and v.prearm_ok  # setpoints still streaming
    fast_forward(v, 1.5)  # the agent stopped streaming
    assert v.mode == FlightMode.OFFBOARD and not v.prearm_ok
    assert v.cmd_arm(True) == ap.DENIED
    assert v.cmd_hold() == ap.ACCEPTED and v.prearm_ok
    fast_forward(v, 0.5)
    assert v.cmd_arm(True) == ap.ACCEPTED
    np.testing.assert_allclose(v.home_ned_m, v.est_position_ned_m)  # home set again at arming (the estimate)
    assert not np.allclose(v.home_ned_m, home)


def test_return_to_launch_climbs_to_the_cone_altitude_returns_and_lands_at_home():
    # PX4 (measured): 8.2 m from home at 6 m, RTL climbed to ~8 m (the 45 deg cone over home), not RTL_RETURN_ALT
    cfg = SimConfig()
    cfg.estimator.pos_bias_std_xy_m = cfg.estimator.pos_bias_std_z_m = 0.0
    v = airborne(cfg=cfg)
    home = v.home_ned_m.copy()
    offboard_at(v, [8.0, 0.0, -6.0], 8.0)
    assert v.cmd_return() == ap.ACCEPTED and v.mode == FlightMode.RETURN
    min_d = 0.0
    for _ in range(600):
        fast_forward(v, 0.1)
        min_d = min(min_d, v.est_position_ned_m[2] - home[2])
        if v.landed:
            break
    assert v.landed
    assert min_d == pytest.approx(-8.0, abs=0.4)
    assert np.linalg.norm(v.est_position_ned_m[:2] - home[:2]) < 0.6


def test_return_altitude_far_from_home_and_descend_altitude():
    cfg = SimConfig(rtl_return_alt_m=12.0, rtl_descend_alt_m=7.0)
    cfg.estimator.pos_bias_std_xy_m = cfg.estimator.pos_bias_std_z_m = 0.0
    v = airborne(cfg=cfg)
    v.params.set("MPC_XY_CRUISE", 8.0)
    offboard_at(v, [30.0, 0.0, -5.0], 9.0)
    home = v.home_ned_m
    ret_d, descend_d = v._rtl_altitudes_d(v.est_position_ned_m)
    assert ret_d - home[2] == pytest.approx(-12.0)  # RTL_RETURN_ALT (the cone is higher 30 m out)
    assert descend_d - home[2] == pytest.approx(-7.0)  # RTL_DESCEND_ALT
    v.params.set("RTL_CONE_ANG", 0)
    assert v._rtl_altitudes_d(np.array([3.0, 0.0, -5.0]))[0] - home[2] == pytest.approx(-12.0)
    # never lower than where it is
    assert v._rtl_altitudes_d(np.array([3.0, 0.0, -20.0]))[0] == pytest.approx(-20.0)


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


def test_position_control_gains_are_px4_parameters():
    v = airborne()
    for name, value in [("MPC_XY_P", 0.95), ("MPC_XY_VEL_P_ACC", 1.8), ("MPC_XY_VEL_I_ACC", 0.4),
                        ("MPC_XY_VEL_D_ACC", 0.2), ("MPC_Z_P", 1.0), ("MPC_Z_VEL_P_ACC", 4.0),
                        ("MPC_Z_VEL_I_ACC", 2.0), ("MPC_TILTMAX_AIR", 45.0)]:
        assert v.params[name] == pytest.approx(value), name  # PX4's defaults
    assert v.params.set("MPC_XY_VEL_P_ACC", 3.0) is not None and v.ctrl.gains.vel_xy_p == 3.0
    assert v.params.set("MPC_XY_P", 0.5) is not None and v.ctrl.gains.pos_xy_p == 0.5
    assert v.cfg.controller.vel_xy_p == 1.8  # the shared configuration is not changed
    for name in ("NAV_RCL_ACT", "NAV_DLL_ACT", "COM_RCL_EXCEPT", "RTL_DESCEND_ALT", "MIS_TAKEOFF_ALT"):
        assert name in v.params


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
