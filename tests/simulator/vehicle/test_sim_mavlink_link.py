"""The MAVLink endpoint over real UDP with a raw pymavlink client: PX4-SITL ports and ids, PARAM, MISSION,
COMMAND_ACK, offboard refusal and offboard-loss failsafe, message intervals, TIMESYNC, and the tick-hook API."""

from __future__ import annotations

import math
import socket
import threading
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink
from sim_vehicle_helpers import free_udp_port, sim_test_config

from simulator.vehicle.params import MAV_PARAM_TYPE_INT32, decode_param_value
from simulator.vehicle.px4_modes import AutoSubMode, MainMode, decode_custom_mode

pytestmark = pytest.mark.timeout(120)
M = mavlink


class RawClient:
    """A minimal MAVLink 2 GCS: listens on ``port`` (like ``udpin://``), replies to whoever sent."""

    def __init__(self, port: int):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        self.sock.settimeout(0.05)
        self.peer = None
        self.backlog: list = []

        class W:
            def write(_, buf):
                self.sock.sendto(buf, self.peer)

        self.mav = mavlink.MAVLink(W(), srcSystem=255, srcComponent=190)

    def close(self):
        self.sock.close()

    def recv(self, duration_s: float) -> list:
        out, t_end = [], time.monotonic() + duration_s
        while time.monotonic() < t_end:
            try:
                data, addr = self.sock.recvfrom(4096)
            except socket.timeout:
                continue
            self.peer = addr
            out += self.mav.parse_buffer(data) or []
        return out

    def wait(self, mtype: str, timeout_s: float = 3.0, pred=lambda m: True):
        """The first matching message; messages received after it in the same batch are kept for later."""
        t_end = time.monotonic() + timeout_s
        while True:
            while self.backlog:
                m = self.backlog.pop(0)
                if m.get_type() == mtype and pred(m):
                    return m
            if time.monotonic() >= t_end:
                raise AssertionError(f"no {mtype} within {timeout_s} s")
            self.backlog += self.recv(0.05)

    def send(self, msg) -> None:
        assert self.peer is not None, "nothing received yet"
        self.mav.send(msg)

    def command(self, sysid: int, cmd: int, *params, timeout_s: float = 2.0) -> int:
        p = list(params) + [0.0] * (7 - len(params))
        self.send(self.mav.command_long_encode(sysid, 1, cmd, 0, *p))
        return self.wait("COMMAND_ACK", timeout_s, lambda m: m.command == cmd).result


@pytest.fixture
def two_vehicles(sim_world_factory):
    cfg = sim_test_config()
    cfg.vehicles.count = 2
    world = sim_world_factory(cfg)
    clients = [RawClient(cfg.ports.offboard_base + i) for i in range(2)]
    yield world, clients
    for c in clients:
        c.close()


def test_px4_sitl_ports_ids_heartbeat_params_mission_unsupported(two_vehicles):
    world, clients = two_vehicles
    for i, c in enumerate(clients):
        hb = c.wait("HEARTBEAT")
        assert hb.get_srcSystem() == i + 1 and hb.get_srcComponent() == 1
        assert hb.autopilot == M.MAV_AUTOPILOT_PX4 and hb.type == M.MAV_TYPE_QUADROTOR
        assert hb.base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and not hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
        assert decode_custom_mode(hb.custom_mode) == (MainMode.AUTO, AutoSubMode.LOITER)
        assert hb.get_msgbuf()[0] == 0xFD  # MAVLink 2 frame

    c = clients[1]
    c.send(c.mav.param_request_list_encode(2, 1))
    values = {}
    t_end = time.monotonic() + 3.0
    count = None
    while time.monotonic() < t_end and (count is None or len(values) < count):
        for m in c.recv(0.1):
            if m.get_type() == "PARAM_VALUE":
                values[m.param_id] = decode_param_value(m.param_value, m.param_type)
                count = m.param_count
    assert count == len(world.vehicles[1].params) and len(values) == count
    assert values["MAV_SYS_ID"] == 2 and values["MIS_TAKEOFF_ALT"] == pytest.approx(2.5)
    # PARAM_SET (bytewise INT32) and PARAM_REQUEST_READ by name
    c.send(c.mav.param_set_encode(2, 1, b"COM_OBL_RC_ACT", struct_int_as_float(4), MAV_PARAM_TYPE_INT32))
    pv = c.wait("PARAM_VALUE", pred=lambda m: m.param_id == "COM_OBL_RC_ACT")
    assert decode_param_value(pv.param_value, pv.param_type) == 4
    c.send(c.mav.param_request_read_encode(2, 1, b"MPC_XY_VEL_MAX", -1))
    assert c.wait("PARAM_VALUE", pred=lambda m: m.param_id == "MPC_XY_VEL_MAX").param_value == pytest.approx(12.0)

    c.send(c.mav.mission_request_list_encode(2, 1, M.MAV_MISSION_TYPE_MISSION))
    assert c.wait("MISSION_COUNT").count == 0
    assert c.command(2, M.MAV_CMD_DO_DIGICAM_CONTROL) == M.MAV_RESULT_UNSUPPORTED
    assert c.command(2, M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION) == M.MAV_RESULT_ACCEPTED
    av = c.wait("AUTOPILOT_VERSION")
    assert av.capabilities & M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    assert av.capabilities & M.MAV_PROTOCOL_CAPABILITY_MAVLINK2

    c.send(c.mav.timesync_encode(0, 123456789))
    ts = c.wait("TIMESYNC", pred=lambda m: m.ts1 == 123456789)
    assert ts.tc1 > 0


def test_ground_station_link_gets_every_vehicle_on_one_port(sim_world_factory):
    cfg = sim_test_config()
    cfg.vehicles.count = 2
    cfg.ports.gcs_port = free_udp_port()
    cfg.ports.gcs_local_base = 0
    gcs = RawClient(cfg.ports.gcs_port)
    api = RawClient(cfg.ports.offboard_base)
    sim_world_factory(cfg)
    try:
        msgs = gcs.recv(2.5)
        api_msgs = api.recv(0.5)
    finally:
        gcs.close()
        api.close()
    # status texts go out on every link
    for ms in (msgs, api_msgs):
        assert any(m.get_type() == "STATUSTEXT" and "GPS fix" in m.text and m.get_srcSystem() == 1 for m in ms)
    heartbeats = {m.get_srcSystem() for m in msgs if m.get_type() == "HEARTBEAT"}
    assert heartbeats == {1, 2}
    att = sum(m.get_type() == "ATTITUDE" and m.get_srcSystem() == 1 for m in msgs)
    assert 20 <= att <= 45  # PX4's lower "normal" rates on the GCS link (15 Hz)


def struct_int_as_float(i: int) -> float:
    import struct

    return struct.unpack("<f", struct.pack("<i", i))[0]


def test_set_message_interval_changes_the_stream_rate(two_vehicles):
    world, clients = two_vehicles
    c = clients[0]
    c.wait("HEARTBEAT")
    n = sum(m.get_type() == "ATTITUDE" for m in c.recv(1.0))
    assert n >= 35  # default 50 Hz
    assert c.command(1, M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ATTITUDE, 100_000) == M.MAV_RESULT_ACCEPTED
    c.recv(0.2)
    n = sum(m.get_type() == "ATTITUDE" for m in c.recv(1.0))
    assert 8 <= n <= 12
    assert c.command(1, M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ATTITUDE, -1) == M.MAV_RESULT_ACCEPTED
    c.recv(0.2)
    assert not any(m.get_type() == "ATTITUDE" for m in c.recv(0.5))
    assert (
        c.command(1, M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_HIGHRES_IMU, 10_000) == M.MAV_RESULT_UNSUPPORTED
    )


def _mode(c):
    return decode_custom_mode(c.wait("HEARTBEAT", 4.0).custom_mode)


def test_offboard_refused_without_setpoints_and_dropped_when_they_stop(two_vehicles):
    world, clients = two_vehicles
    c = clients[0]
    c.wait("HEARTBEAT")
    c.wait("SYS_STATUS", 4.0, lambda m: m.onboard_control_sensors_health & M.MAV_SYS_STATUS_PREARM_CHECK)
    # COM_OF_LOSS_T 1.0 s (PX4's default; set as the agent does)
    c.send(c.mav.param_set_encode(1, 1, b"COM_OF_LOSS_T", 1.0, M.MAV_PARAM_TYPE_REAL32))
    c.wait("PARAM_VALUE", pred=lambda m: m.param_id == "COM_OF_LOSS_T" and m.param_value == 1.0)
    offboard = (M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MainMode.OFFBOARD, 0)
    assert c.command(1, M.MAV_CMD_DO_SET_MODE, *offboard) == M.MAV_RESULT_TEMPORARILY_REJECTED
    assert c.command(1, M.MAV_CMD_COMPONENT_ARM_DISARM, 1.0) == M.MAV_RESULT_ACCEPTED
    assert c.command(1, M.MAV_CMD_NAV_TAKEOFF, *([math.nan] * 7)) == M.MAV_RESULT_ACCEPTED
    c.wait("LOCAL_POSITION_NED", 10.0, lambda m: m.z < -2.0)
    mask = 0b0000_1111_1111_1000  # position + yaw only (as MAVSDK set_position_ned)
    stop = threading.Event()

    def stream():
        while not stop.is_set():
            c.mav.send(
                c.mav.set_position_target_local_ned_encode(
                    0, 1, 1, M.MAV_FRAME_LOCAL_NED, mask, 3.0, 0.0, -3.0, 0, 0, 0, 0, 0, 0, 0.0, 0.0
                )
            )
            time.sleep(0.05)

    th = threading.Thread(target=stream, daemon=True)
    th.start()
    try:
        time.sleep(0.3)
        assert c.command(1, M.MAV_CMD_DO_SET_MODE, *offboard) == M.MAV_RESULT_ACCEPTED
        c.wait("LOCAL_POSITION_NED", 8.0, lambda m: abs(m.x - 3.0) < 0.5 and abs(m.z + 3.0) < 0.5)
        assert _mode(c) == (MainMode.OFFBOARD, 0)
        assert world.vehicles[0].mode.name == "OFFBOARD"
    finally:
        stop.set()
        th.join()
    t_stop = time.monotonic()
    # PX4: no setpoint for COM_OF_LOSS_T -> failsafe; COM_OBL_RC_ACT 0 without RC = Return; STATUSTEXT tells why
    txt = c.wait("STATUSTEXT", 4.0, lambda m: "failsafe" in m.text.lower())
    assert 0.9 < time.monotonic() - t_stop < 3.0
    assert "no offboard signal" in txt.text
    assert _mode(c) == (MainMode.AUTO, AutoSubMode.RTL)
    ack = c.command(1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0.0)
    assert ack == M.MAV_RESULT_DENIED  # in the air
    assert c.command(1, M.MAV_CMD_NAV_LAND) == M.MAV_RESULT_ACCEPTED
    assert _mode(c) == (MainMode.AUTO, AutoSubMode.LAND)
    gp = c.wait("GLOBAL_POSITION_INT")
    assert gp.relative_alt > 1000 and abs(gp.lat * 1e-7 - world.cfg.origin.lat_deg) < 1e-3


def test_tick_hooks_see_the_truth(sim_world_factory):
    cfg = sim_test_config()
    cfg.vehicles.count = 3
    world = sim_world_factory(cfg)
    calls = []
    lock = threading.Event()

    def hook(t_ns, truths):
        calls.append((t_ns, truths))
        if len(calls) >= 20:
            lock.set()

    t0 = time.monotonic()
    world.add_tick_hook(hook, rate_hz=20)
    assert lock.wait(3.0)
    elapsed = time.monotonic() - t0
    world.remove_tick_hook(hook)
    assert 0.8 < elapsed < 2.5  # 20 calls at 20 Hz
    t_ns, truths = calls[-1]
    assert abs(t_ns - time.time_ns()) < 1e9
    assert [tr.system_id for tr in truths] == [1, 2, 3]
    for i, tr in enumerate(truths):
        np.testing.assert_allclose(tr.position_ned_m, [0.0, 3.0 * i, 0.0])  # default spawn line, on the ground
        assert tr.R_world_body.shape == (3, 3) and tr.velocity_ned_m_s.shape == (3,)
        assert tr.landed and not tr.armed and tr.flight_mode == "HOLD"
        assert tr.t_sim_s > 0.5 and tr.battery_percent > 99.0
        assert np.linalg.norm(tr.est_position_ned_m - tr.position_ned_m) < 6.0  # estimate = truth + ~1 m bias

    def bad_hook(t_ns, truths):
        raise RuntimeError("boom")

    world.add_tick_hook(bad_hook)
    time.sleep(0.2)
    assert all(h.fn is not bad_hook for h in world._hooks)  # removed, simulation goes on
    assert world.ticks > 0 and world._thread is not None and world._thread.is_alive()
