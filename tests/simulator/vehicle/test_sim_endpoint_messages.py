"""The MAVLink adapter's decoding of setpoint messages and commands, driven without sockets and faster than
real time: messages are packed by a client pymavlink, parsed back, and fed to ``MavlinkEndpoint.handle``."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink
from sim_vehicle_helpers import fast_forward

from simulator.config import RatesConfig, SimConfig
from simulator.vehicle.autopilot import SimVehicle
from simulator.vehicle.mavlink_endpoint import MavlinkEndpoint
from simulator.vehicle.px4_modes import FlightMode, MainMode
from skycap import frames
from skycap.frames import ned_to_geodetic

M = mavlink


class Capture:
    """Stands in for the UDP transport: keeps what the endpoint sends, decoded."""

    def __init__(self):
        self.parser = mavlink.MAVLink(None, 255, 190)
        self.msgs = []

    def is_closing(self):
        return False

    def sendto(self, buf, addr):
        self.msgs += self.parser.parse_buffer(buf) or []


class Rig:
    def __init__(self, **cfg_changes):
        cfg = SimConfig()
        cfg.estimator.pos_bias_std_xy_m = cfg.estimator.pos_bias_std_z_m = 0.0
        cfg.estimator.att_noise_std_deg = 0.0
        for k, v in cfg_changes.items():
            obj, *path = k.split("__")
            setattr(getattr(cfg, obj), path[0], v) if path else setattr(cfg, obj, v)
        self.cfg = cfg.validate()
        self.v = SimVehicle(0, self.cfg)
        self.ep = MavlinkEndpoint(self.v, ("127.0.0.1", 9), RatesConfig(), clock=lambda: self.v.t_s)
        self.ep.transport = self.out = Capture()
        self.client = mavlink.MAVLink(None, 255, 190)

    def feed(self, msg) -> None:
        for m in mavlink.MAVLink(None, 255, 190).parse_buffer(msg.pack(self.client)) or []:
            self.ep.handle(m)

    def command(self, cmd, *p, use_int=False, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, x=0, y=0, z=0.0) -> int:
        p = list(p) + [0.0] * (7 - len(p))
        if use_int:
            msg = self.client.command_int_encode(1, 1, frame, cmd, 0, 0, *p[:4], x, y, z)
        else:
            msg = self.client.command_long_encode(1, 1, cmd, 0, *p)
        self.out.msgs.clear()
        self.feed(msg)
        acks = [m for m in self.out.msgs if m.get_type() == "COMMAND_ACK" and m.command == cmd]
        assert len(acks) == 1 and acks[0].target_system == 255 and acks[0].target_component == 190
        return acks[0].result

    def takeoff(self):
        fast_forward(self.v, 1.2)
        assert self.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1.0) == M.MAV_RESULT_ACCEPTED
        assert self.command(M.MAV_CMD_NAV_TAKEOFF, *([math.nan] * 7)) == M.MAV_RESULT_ACCEPTED
        fast_forward(self.v, 6.0)
        assert self.v.mode == FlightMode.HOLD

    def offboard(self, make_msg, seconds):
        self.feed(make_msg())
        assert (
            self.command(M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MainMode.OFFBOARD)
            == M.MAV_RESULT_ACCEPTED
        )
        n = [0]

        def each(v):
            n[0] += 1
            if n[0] % 10 == 0:  # 10 Hz stream
                self.feed(make_msg())

        fast_forward(self.v, seconds, each_step=each)
        assert self.v.mode == FlightMode.OFFBOARD


def test_attitude_target_tilts_and_accelerates_the_vehicle():
    r = Rig()
    r.takeoff()
    roll = math.radians(10.0)
    q = [math.cos(roll / 2), math.sin(roll / 2), 0.0, 0.0]  # 10 deg right roll, heading north
    mask = 0b0000_0111  # body rates ignored
    r.offboard(lambda: r.client.set_attitude_target_encode(0, 1, 1, mask, q, 0, 0, 0, 0.52), 2.0)
    roll_now, _, _ = frames.euler_from_R(r.v.truth.R_world_body)
    assert math.degrees(roll_now) == pytest.approx(10.0, abs=0.5)
    assert r.v.truth.velocity_ned_m_s[1] > 2.0  # rolled right -> accelerates east


def test_body_frame_velocity_is_rotated_by_heading():
    r = Rig(vehicles__spawn_yaw_deg=90.0)  # facing east
    r.takeoff()
    mask = 0b0000_1101_1100_0111  # velocity + yaw rate(ignored) only
    r.offboard(
        lambda: r.client.set_position_target_local_ned_encode(
            0, 1, 1, M.MAV_FRAME_BODY_NED, mask, 0, 0, 0, 2.0, 0, 0, 0, 0, 0, 0, 0
        ),
        4.0,
    )
    np.testing.assert_allclose(r.v.truth.velocity_ned_m_s, [0.0, 2.0, 0.0], atol=0.1)


def test_odometry_on_request_has_body_frame_velocity():
    r = Rig(vehicles__spawn_yaw_deg=90.0)
    r.takeoff()
    mask = 0b0000_1101_1100_0111
    r.offboard(
        lambda: r.client.set_position_target_local_ned_encode(
            0, 1, 1, M.MAV_FRAME_LOCAL_NED, mask, 0, 0, 0, 0.0, 2.0, 0, 0, 0, 0, 0, 0
        ),
        4.0,
    )
    assert r.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ODOMETRY, 20_000) == M.MAV_RESULT_ACCEPTED
    r.out.msgs.clear()
    r.ep.tick(r.v.t_s)
    odo = [m for m in r.out.msgs if m.get_type() == "ODOMETRY"]
    assert len(odo) == 1
    o = odo[0]
    assert o.frame_id == M.MAV_FRAME_LOCAL_NED and o.child_frame_id == M.MAV_FRAME_BODY_FRD
    assert o.vx == pytest.approx(2.0, abs=0.15) and abs(o.vy) < 0.15  # flying east, nose east: forward
    np.testing.assert_allclose([o.x, o.y, o.z], r.v.est_local_position_ned_m, atol=1e-3)


def test_global_position_target_relative_altitude():
    r = Rig()
    r.takeoff()
    o = r.cfg.origin
    lat, lon, _ = ned_to_geodetic(np.array([6.0, -4.0, 0.0]), o.lat_deg, o.lon_deg, o.alt_m)
    mask = 0b0000_1101_1111_1000  # position + yaw
    r.offboard(
        lambda: r.client.set_position_target_global_int_encode(
            0,
            1,
            1,
            M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
            mask,
            int(round(float(lat) * 1e7)),
            int(round(float(lon) * 1e7)),
            7.0,
            0,
            0,
            0,
            0,
            0,
            0,
            0.0,
            0.0,
        ),
        10.0,
    )
    np.testing.assert_allclose(r.v.truth.position_ned_m, [6.0, -4.0, -7.0], atol=0.15)


def test_reposition_command_int_and_change_speed():
    r = Rig()
    r.takeoff()
    o = r.cfg.origin
    lat, lon, _ = ned_to_geodetic(np.array([-10.0, 0.0, 0.0]), o.lat_deg, o.lon_deg, o.alt_m)
    assert r.command(M.MAV_CMD_DO_CHANGE_SPEED, 1, 2.0) == M.MAV_RESULT_ACCEPTED
    res = r.command(
        M.MAV_CMD_DO_REPOSITION,
        -1,
        M.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE,
        0,
        math.nan,
        use_int=True,
        frame=M.MAV_FRAME_GLOBAL_INT,
        x=int(round(float(lat) * 1e7)),
        y=int(round(float(lon) * 1e7)),
        z=o.alt_m + 4.0,
    )
    assert res == M.MAV_RESULT_ACCEPTED and r.v.mode == FlightMode.HOLD
    speeds = []
    fast_forward(r.v, 9.0, each_step=lambda v: speeds.append(math.hypot(*v.truth.velocity_ned_m_s[:2])))
    np.testing.assert_allclose(r.v.truth.position_ned_m, [-10.0, 0.0, -4.0], atol=0.2)
    assert max(speeds) > 4.0  # MPC_XY_CRUISE (5 m/s): the reposition sets its own speed


def test_requests_params_and_unsupported():
    r = Rig()
    fast_forward(r.v, 1.2)
    assert r.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_HOME_POSITION) == M.MAV_RESULT_ACCEPTED
    home = [m for m in r.out.msgs if m.get_type() == "HOME_POSITION"]
    assert len(home) == 1 and home[0].latitude == pytest.approx(r.cfg.origin.lat_deg * 1e7, abs=2)
    assert r.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN) == M.MAV_RESULT_ACCEPTED
    assert r.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_HIGHRES_IMU) == M.MAV_RESULT_UNSUPPORTED
    assert r.command(M.MAV_CMD_GET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ATTITUDE) == M.MAV_RESULT_ACCEPTED
    mi = [m for m in r.out.msgs if m.get_type() == "MESSAGE_INTERVAL"]
    assert mi[0].interval_us == 20000
    assert r.command(M.MAV_CMD_DO_FLIGHTTERMINATION, 1) == M.MAV_RESULT_UNSUPPORTED
    assert r.command(M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1) == M.MAV_RESULT_UNSUPPORTED
    r.out.msgs.clear()
    r.feed(r.client.param_request_read_encode(1, 1, b"", 0))
    assert r.out.msgs[0].param_id == "MIS_TAKEOFF_ALT" and r.out.msgs[0].param_index == 0
    r.out.msgs.clear()
    r.feed(r.client.param_set_encode(1, 1, b"NOT_A_PARAM", 1.0, M.MAV_PARAM_TYPE_REAL32))
    assert r.out.msgs == []  # PX4 ignores unknown names
    r.feed(r.client.command_long_encode(1, 100, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    r.feed(r.client.command_long_encode(7, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    assert r.out.msgs == [] and not r.v.armed  # other component / other system: not for us


def test_home_is_the_ground_at_the_spawn_and_relative_altitude_is_above_it():
    r = Rig(vehicles__spawn_ne_m=[[4.0, -2.0]])
    fast_forward(r.v, 1.2)
    o = r.cfg.origin
    r.out.msgs.clear()
    assert r.ep.send_stream("HOME_POSITION") and r.ep.send_stream("GLOBAL_POSITION_INT")
    home = next(m for m in r.out.msgs if m.get_type() == "HOME_POSITION")
    lat, lon, alt = ned_to_geodetic(np.array([4.0, -2.0, 0.0]), o.lat_deg, o.lon_deg, o.alt_m)
    # the ground at the spawn (within the estimator's 2 cm noise; 1e-7 deg ~ 1.1 cm)
    assert home.latitude == pytest.approx(float(lat) * 1e7, abs=10)
    assert home.longitude == pytest.approx(float(lon) * 1e7, abs=15)
    assert home.altitude == pytest.approx(o.alt_m * 1000, abs=100)
    assert (home.x, home.y) == pytest.approx((0.0, 0.0), abs=0.05)  # local frame: the EKF origin is the spawn
    gp = next(m for m in r.out.msgs if m.get_type() == "GLOBAL_POSITION_INT")
    assert abs(gp.relative_alt) < 100
    r.takeoff()  # MIS_TAKEOFF_ALT 2.5 m above home (set again at arming)
    r.out.msgs.clear()
    r.ep.send_stream("GLOBAL_POSITION_INT")
    gp = next(m for m in r.out.msgs if m.get_type() == "GLOBAL_POSITION_INT")
    assert gp.relative_alt == pytest.approx(2500, abs=150)
    assert gp.alt - gp.relative_alt == pytest.approx(o.alt_m * 1000, abs=100)


def test_sys_status_prearm_clear_in_offboard_without_setpoints():
    r = Rig()
    fast_forward(r.v, 1.2)
    r.v._set_mode(FlightMode.OFFBOARD)  # e.g. landed and disarmed from Offboard, the agent no longer streaming
    r.out.msgs.clear()
    r.ep.send_stream("SYS_STATUS")
    st = next(m for m in r.out.msgs if m.get_type() == "SYS_STATUS")
    assert not st.onboard_control_sensors_health & M.MAV_SYS_STATUS_PREARM_CHECK
    assert r.command(M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MainMode.AUTO, 3) == M.MAV_RESULT_ACCEPTED
    r.out.msgs.clear()
    r.ep.send_stream("SYS_STATUS")
    st = next(m for m in r.out.msgs if m.get_type() == "SYS_STATUS")
    assert st.onboard_control_sensors_health & M.MAV_SYS_STATUS_PREARM_CHECK


def test_simulated_link_loss_drops_both_ways_for_its_window():
    r = Rig()
    r.ep.schedule_link_loss(r.v.t_s + 1.0, 3.0)
    ping = r.client.ping_encode(0, 1, 0, 0).pack(r.client)
    r.ep.tick(r.v.t_s)
    r.ep.datagram_received(ping, ("127.0.0.1", 9))
    n_before = len(r.out.msgs)
    assert n_before > 0 and r.ep.link_loss_dropped == {"sent": 0, "received": 0}
    fast_forward(r.v, 2.0)  # inside the window
    r.ep.tick(r.v.t_s)
    r.ep.datagram_received(ping, ("127.0.0.1", 9))
    assert len(r.out.msgs) == n_before  # nothing sent
    assert r.ep.link_loss_dropped["sent"] > 0 and r.ep.link_loss_dropped["received"] == 1
    fast_forward(r.v, 3.0)  # after it
    r.ep.tick(r.v.t_s)
    assert len(r.out.msgs) > n_before
