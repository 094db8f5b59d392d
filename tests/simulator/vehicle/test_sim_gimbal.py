"""The simulated gimbal's dynamics (pure, stepped faster than real time): limits, rate limit, lag, yaw modes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from simulator.config import SimConfig
from simulator.vehicle.autopilot import SimVehicle
from simulator.vehicle.gimbal import GimbalConfig, SimGimbal
from skycap.config import ConfigError

D = math.radians
DT = 0.01


def run(g: SimGimbal, seconds: float, vehicle_yaw_rad=lambda t: 0.0) -> list[tuple[float, float, float]]:
    """(t, pitch, yaw) after each step."""
    out, t = [], 0.0
    for _ in range(int(round(seconds / DT))):
        t += DT
        g.step(DT, vehicle_yaw_rad(t))
        out.append((t, g.pitch_rad, g.yaw_rad))
    return out


def settle_time_s(trace, target_rad: float, axis: int = 1, tol_rad: float = D(1.0)) -> float:
    """First time after which the axis stays within ``tol_rad`` of the target."""
    for i, row in enumerate(trace):
        if all(abs(r[axis] - target_rad) <= tol_rad for r in trace[i:]):
            return row[0]
    return math.inf


def test_a_step_is_rate_limited_then_lags_in_and_settles_exactly():
    g = SimGimbal(GimbalConfig(max_rate_deg_s=90.0, time_constant_s=0.1))
    g.set_angles(D(-60.0), 0.0)
    tr = run(g, 2.0)
    rates = [abs(b[1] - a[1]) / DT for a, b in zip(tr, tr[1:])]
    assert max(rates) <= D(90.0) + 1e-9
    assert abs(tr[0][1] - (-D(0.9))) < 1e-9  # the first 10 ms at the rate limit: 0.9 deg
    t_settle = settle_time_s(tr, D(-60.0))
    # 60 deg at 90 deg/s = 0.67 s (less the last part, inside the lag) + the lag's tail from 9 deg to 1 deg (tau ln 9)
    assert 0.55 < t_settle < 0.67 + 0.1 * math.log(9.0) + 0.05, t_settle
    assert abs(tr[-1][1] - D(-60.0)) < 1e-6  # no steady error
    assert abs(g.pitch_rate_rad_s) < 1e-4


def test_small_step_is_a_pure_first_order_lag():
    g = SimGimbal(GimbalConfig(time_constant_s=0.2))
    g.set_angles(D(-5.0), 0.0)
    tr = run(g, 0.2)
    # after one time constant: 1 - 1/e of the way
    assert abs(tr[-1][1] / D(-5.0) - (1 - math.exp(-1))) < 1e-6


def test_targets_are_clamped_to_the_limits():
    g = SimGimbal(GimbalConfig(pitch_min_deg=-90.0, pitch_max_deg=30.0, yaw_min_deg=-120.0, yaw_max_deg=120.0))
    g.set_angles(D(-135.0), D(170.0))
    run(g, 4.0)
    assert g.pitch_rad == pytest.approx(D(-90.0)) and g.yaw_rad == pytest.approx(D(120.0))
    g.set_angles(D(60.0), D(-500.0))
    run(g, 6.0)
    assert g.pitch_rad == pytest.approx(D(30.0)) and g.yaw_rad == pytest.approx(D(-120.0))


def test_yaw_follow_turns_with_the_vehicle_and_yaw_lock_holds_north():
    turn = lambda t: D(30.0) * min(t, 1.0)  # the vehicle yaws 30 deg in 1 s  # noqa: E731
    g = SimGimbal(GimbalConfig())
    g.set_angles(D(-20.0), D(10.0), yaw_lock=False)
    run(g, 3.0, turn)
    assert g.yaw_rad == pytest.approx(D(10.0), abs=1e-6)  # relative to the heading: unchanged by the turn
    g = SimGimbal(GimbalConfig())
    g.set_angles(D(-20.0), D(10.0), yaw_lock=True, vehicle_yaw_rad=0.0)  # 10 deg east of north
    run(g, 3.0, turn)
    assert g.yaw_rad == pytest.approx(D(10.0 - 30.0), abs=1e-6)  # counter-turned: still 10 deg from north
    assert g.yaw_rad + turn(3.0) == pytest.approx(D(10.0), abs=1e-6)


def test_yaw_has_end_stops_and_does_not_wrap_through_them():
    g = SimGimbal(GimbalConfig(time_constant_s=0.0))
    g.set_angles(0.0, D(170.0))
    run(g, 3.0)
    g.set_angles(0.0, D(-170.0))
    tr = run(g, 0.5)
    assert all(-math.pi <= y <= math.pi for _, _, y in tr)
    assert tr[0][2] < D(170.0)  # went back through 0, not across +-180


def test_rate_commands_move_the_target_within_the_rate_limit():
    g = SimGimbal(GimbalConfig(time_constant_s=0.0, max_rate_deg_s=90.0))
    g.set_rates(D(-20.0), D(500.0))  # yaw rate beyond the limit: clamped
    run(g, 1.0)
    assert g.pitch_rad == pytest.approx(D(-20.0), abs=1e-6)
    assert g.yaw_rad == pytest.approx(D(90.0), abs=1e-6)


def test_config_validation_and_the_vehicle_steps_its_gimbal():
    with pytest.raises(ConfigError):
        GimbalConfig(pitch_min_deg=10.0, pitch_max_deg=0.0).validate()
    with pytest.raises(ConfigError):
        GimbalConfig(initial_pitch_deg=-100.0).validate()
    cfg = SimConfig()
    cfg.gimbal.initial_pitch_deg = -30.0
    v = SimVehicle(0, cfg.validate())
    assert v.gimbal is not None and v.gimbal.pitch_rad == pytest.approx(D(-30.0))
    v.gimbal.set_angles(D(-45.0), D(20.0))
    for _ in range(200):
        v.step(v.t_s + DT, DT, np.zeros(3))
    snap = v.truth_snapshot(0)
    assert snap.gimbal_pitch_rad == pytest.approx(D(-45.0), abs=1e-4) and snap.gimbal_yaw_rad == pytest.approx(D(20.0), abs=1e-4)
    cfg.gimbal.enabled = False
    v = SimVehicle(0, cfg)
    assert v.gimbal is None and v.truth_snapshot(0).gimbal_pitch_rad is None


# ---------------------------------------------------------------------- the protocol, without sockets
def test_endpoint_speaks_gimbal_protocol_v2_as_the_gimbal_manager():
    from pymavlink.dialects.v20 import common as mavlink
    from sim_vehicle_helpers import fast_forward
    from test_sim_endpoint_messages import Rig

    M = mavlink
    r = Rig()
    assert r.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_GIMBAL_MANAGER_INFORMATION) == M.MAV_RESULT_ACCEPTED
    info = [m for m in r.out.msgs if m.get_type() == "GIMBAL_MANAGER_INFORMATION"]
    assert len(info) == 1 and info[0].gimbal_device_id == 1
    assert info[0].pitch_min == pytest.approx(D(-90.0)) and info[0].pitch_max == pytest.approx(D(30.0))
    assert r.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_GIMBAL_DEVICE_INFORMATION) == M.MAV_RESULT_ACCEPTED
    # control: the client (255/190) takes primary control; another component is then refused
    assert r.command(M.MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, -2, -2, -1, -1, 0, 0, 1) == M.MAV_RESULT_ACCEPTED
    status = [m for m in r.out.msgs if m.get_type() == "GIMBAL_MANAGER_STATUS"]
    assert status and (status[-1].primary_control_sysid, status[-1].primary_control_compid) == (255, 190)
    other = mavlink.MAVLink(None, 1, 191)
    r.out.msgs.clear()
    for m in mavlink.MAVLink(None, 1, 191).parse_buffer(
            other.command_long_encode(1, 1, M.MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, 0, -10, 0, math.nan, math.nan, 0, 0,
                                      1).pack(other)) or []:
        r.ep.handle(m)
    assert [m.result for m in r.out.msgs if m.get_type() == "COMMAND_ACK"] == [M.MAV_RESULT_DENIED]
    # wrong gimbal device id: denied; angles as COMMAND_INT (flags in x, device id in z)
    assert r.command(M.MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, -30, 0, math.nan, math.nan, 0, 0, 7) == M.MAV_RESULT_DENIED
    assert r.command(M.MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, -30, 15, math.nan, math.nan, use_int=True, frame=0, x=0,
                     z=1.0) == M.MAV_RESULT_ACCEPTED
    fast_forward(r.v, 2.0)
    r.out.msgs.clear()
    r.ep.send_stream("GIMBAL_DEVICE_ATTITUDE_STATUS")
    (st,) = [m for m in r.out.msgs if m.get_type() == "GIMBAL_DEVICE_ATTITUDE_STATUS"]
    from skycap.frames import R_from_quat_wxyz, euler_from_R

    roll, pitch, yaw = euler_from_R(R_from_quat_wxyz(list(st.q)))
    assert (math.degrees(roll), math.degrees(pitch), math.degrees(yaw)) == pytest.approx((0.0, -30.0, 15.0), abs=1e-3)
    assert st.gimbal_device_id == 1 and st.flags & M.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME
    # GIMBAL_MANAGER_SET_PITCHYAW message (stream), yaw locked to north
    r.feed(r.client.gimbal_manager_set_pitchyaw_encode(1, 1, M.GIMBAL_MANAGER_FLAGS_YAW_LOCK, 1, D(-5.0), D(40.0),
                                                       math.nan, math.nan))
    assert r.v.gimbal.yaw_lock and r.v.gimbal.target_yaw_rad == pytest.approx(D(40.0))
    # without a gimbal: nothing offered
    r2 = Rig(gimbal__enabled=False)
    assert r2.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_GIMBAL_MANAGER_INFORMATION) == M.MAV_RESULT_UNSUPPORTED
    assert not r2.ep.send_stream("GIMBAL_DEVICE_ATTITUDE_STATUS")
