"""MAVLink 2 over UDP for one :class:`~simulator.vehicle.autopilot.SimVehicle`, the way PX4 SITL talks.

A thin adapter: it decodes incoming messages (pymavlink, ``common`` dialect) into calls on the vehicle,
and streams the vehicle's *estimated* state at configured rates. Like PX4's ``mavlink`` module in UDP
mode it sends to a configured remote (``127.0.0.1:14540+i`` for the offboard/API link) from a bound
local port (``14580+i``), and switches its remote to whoever last sent it a packet.

Handled (see ``simulator/vehicle/README.md`` for the full list): HEARTBEAT, COMMAND_LONG/COMMAND_INT
(arm/disarm, takeoff, land, return, hold/loiter, do_set_mode, do_reposition, do_change_speed,
set/get_message_interval, request_message, request_autopilot_capabilities, get_home_position,
do_set_home; everything else -> MAV_RESULT_UNSUPPORTED), SET_POSITION_TARGET_LOCAL_NED,
SET_POSITION_TARGET_GLOBAL_INT, SET_ATTITUDE_TARGET, PARAM_REQUEST_LIST/READ, PARAM_SET,
MISSION_REQUEST_LIST (answers an empty mission), MISSION_CLEAR_ALL, MISSION_COUNT (upload refused),
TIMESYNC; the gimbal protocol v2 as PX4 speaks it for a non-MAVLink gimbal (the autopilot is the gimbal manager
of gimbal device 1): GIMBAL_MANAGER_INFORMATION / GIMBAL_DEVICE_INFORMATION on request,
MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE / _PITCHYAW, GIMBAL_MANAGER_SET_ATTITUDE / _SET_PITCHYAW, streams of
GIMBAL_DEVICE_ATTITUDE_STATUS and GIMBAL_MANAGER_STATUS.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from simulator.config import RatesConfig
from simulator.vehicle import autopilot as ap
from simulator.vehicle.autopilot import SimVehicle
from skycap.frames import R_from_quat_wxyz, euler_from_R, quat_wxyz_from_R, yaw_from_R
from simulator.vehicle.controller import TrajectorySetpoint
from simulator.vehicle.dynamics import GRAVITY_M_S2
from simulator.vehicle.gimbal import quat_wxyz_from_pitch_yaw
from simulator.vehicle.params import decode_param_value, encode_param_value
from simulator.vehicle.px4_modes import encode_custom_mode, heartbeat_base_mode
from skycap.frames import geodetic_to_ned

log = logging.getLogger(__name__)

M = mavlink
AUTOPILOT_COMPONENT_ID = M.MAV_COMP_ID_AUTOPILOT1
#: PX4 v1.15.0 release, encoded as AUTOPILOT_VERSION.flight_sw_version (major, minor, patch, type=255 official)
PX4_VERSION = (1 << 24) | (15 << 16) | (0 << 8) | 255
CAPABILITIES = (
    M.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
    | M.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | M.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    | M.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
    | M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
    | M.MAV_PROTOCOL_CAPABILITY_MAVLINK2
)
_S = M  # sensor bits
SENSORS_PRESENT = (
    _S.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | _S.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | _S.MAV_SYS_STATUS_SENSOR_3D_MAG
    | _S.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | _S.MAV_SYS_STATUS_SENSOR_GPS
    | _S.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | _S.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | _S.MAV_SYS_STATUS_SENSOR_YAW_POSITION
    | _S.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | _S.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | _S.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | _S.MAV_SYS_STATUS_AHRS
    | _S.MAV_SYS_STATUS_SENSOR_BATTERY
    | _S.MAV_SYS_STATUS_PREARM_CHECK
)

# stream name -> (message id, RatesConfig field)
STREAMS = {
    "HEARTBEAT": (M.MAVLINK_MSG_ID_HEARTBEAT, "heartbeat_hz"),
    "SYS_STATUS": (M.MAVLINK_MSG_ID_SYS_STATUS, "sys_status_hz"),
    "BATTERY_STATUS": (M.MAVLINK_MSG_ID_BATTERY_STATUS, "battery_hz"),
    "EXTENDED_SYS_STATE": (M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, "extended_sys_state_hz"),
    "ATTITUDE": (M.MAVLINK_MSG_ID_ATTITUDE, "attitude_hz"),
    "ATTITUDE_QUATERNION": (M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, "attitude_quaternion_hz"),
    "LOCAL_POSITION_NED": (M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, "local_position_hz"),
    "GLOBAL_POSITION_INT": (M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, "global_position_hz"),
    "GPS_RAW_INT": (M.MAVLINK_MSG_ID_GPS_RAW_INT, "gps_raw_hz"),
    "HOME_POSITION": (M.MAVLINK_MSG_ID_HOME_POSITION, "home_position_hz"),
    "VFR_HUD": (M.MAVLINK_MSG_ID_VFR_HUD, "vfr_hud_hz"),
    "SYSTEM_TIME": (M.MAVLINK_MSG_ID_SYSTEM_TIME, "system_time_hz"),
    "GPS_GLOBAL_ORIGIN": (M.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, "gps_global_origin_hz"),
    "ODOMETRY": (M.MAVLINK_MSG_ID_ODOMETRY, "odometry_hz"),
    "GIMBAL_DEVICE_ATTITUDE_STATUS": (M.MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS, "gimbal_device_attitude_status_hz"),
    "GIMBAL_MANAGER_STATUS": (M.MAVLINK_MSG_ID_GIMBAL_MANAGER_STATUS, "gimbal_manager_status_hz"),
}
GIMBAL_STREAMS = ("GIMBAL_DEVICE_ATTITUDE_STATUS", "GIMBAL_MANAGER_STATUS")
#: the gimbal device id the autopilot manages: 1..6 = a non-MAVLink gimbal behind the autopilot (PX4 with a
#: PWM/serial gimbal); MAVSDK then addresses the manager (the autopilot) with this device id
GIMBAL_DEVICE_ID = 1
GIMBAL_CAP_FLAGS = (
    M.GIMBAL_MANAGER_CAP_FLAGS_HAS_ROLL_LOCK
    | M.GIMBAL_MANAGER_CAP_FLAGS_HAS_PITCH_AXIS
    | M.GIMBAL_MANAGER_CAP_FLAGS_HAS_PITCH_LOCK
    | M.GIMBAL_MANAGER_CAP_FLAGS_HAS_YAW_AXIS
    | M.GIMBAL_MANAGER_CAP_FLAGS_HAS_YAW_FOLLOW
    | M.GIMBAL_MANAGER_CAP_FLAGS_HAS_YAW_LOCK
    | M.GIMBAL_MANAGER_CAP_FLAGS_SUPPORTS_YAW_IN_EARTH_FRAME
)
MSGID_TO_STREAM = {mid: name for name, (mid, _) in STREAMS.items()}
#: rates of PX4's "normal" (ground-station) MAVLink instance
GCS_RATES = RatesConfig(
    heartbeat_hz=1.0,
    sys_status_hz=1.0,
    battery_hz=0.5,
    extended_sys_state_hz=1.0,
    attitude_hz=15.0,
    attitude_quaternion_hz=0.0,
    local_position_hz=1.0,
    global_position_hz=5.0,
    gps_raw_hz=1.0,
    home_position_hz=0.5,
    vfr_hud_hz=4.0,
    system_time_hz=1.0,
    gps_global_origin_hz=0.0,
    gimbal_device_attitude_status_hz=5.0,
    gimbal_manager_status_hz=1.0,
)


class _Writer:
    """File-like sink for pymavlink's ``MAVLink.send``: one datagram per message."""

    def __init__(self, endpoint: "MavlinkEndpoint"):
        self.endpoint = endpoint

    def write(self, buf: bytes) -> None:
        self.endpoint._sendto(buf)


class MavlinkEndpoint(asyncio.DatagramProtocol):
    """One MAVLink UDP link of one vehicle.

    Args:
        vehicle: the simulated vehicle it speaks for.
        remote: (host, port) to stream to until a partner sends something.
        rates: message rates of this link (Hz; 0 = off).
        clock: ``() -> seconds since simulation start`` (the runner's monotonic clock).
        name: for logs ("offboard" / "gcs").
    """

    def __init__(self, vehicle: SimVehicle, remote: tuple[str, int], rates: RatesConfig, clock, name: str = "offboard"):
        self.vehicle = vehicle
        self.remote = remote
        self.clock = clock
        self.name = name
        self.transport: asyncio.DatagramTransport | None = None
        self.mav = mavlink.MAVLink(_Writer(self), srcSystem=vehicle.system_id, srcComponent=AUTOPILOT_COMPONENT_ID)
        self.mav.robust_parsing = True
        self._reply_to: tuple[str, int] | None = None
        self.default_period_s = {
            name: (1.0 / getattr(rates, field) if getattr(rates, field) > 0 else math.inf)
            for name, (_, field) in STREAMS.items()
        }
        self.period_s = dict(self.default_period_s)
        self._next_due = {name: 0.0 for name in STREAMS}
        self.sent_counts = {name: 0 for name in STREAMS}
        self.received_counts: dict[str, int] = {}
        self._texts_sent = vehicle.status_count
        self.command_log: list[tuple[int, int]] = []  # (MAV_CMD, MAV_RESULT) of every command answered
        self._last_partner_log = 0.0
        #: simulated link losses (fault injection, :meth:`schedule_link_loss`): [(from_s, until_s)] in simulation
        #: time; meanwhile nothing is sent and every datagram received is discarded (counted here)
        self.link_losses: list[tuple[float, float]] = []
        self.link_loss_dropped = {"sent": 0, "received": 0}
        self._link_was_down = False

    def schedule_link_loss(self, at_s: float, for_s: float) -> None:
        """Fault injection: this link carries nothing, either way, from simulation time ``at_s`` for ``for_s``."""
        self.link_losses.append((float(at_s), float(at_s) + float(for_s)))

    def link_down(self) -> bool:
        """Whether a simulated link loss is in progress (logs its start and end)."""
        if not self.link_losses:
            return False
        t = self.clock()
        down = any(a <= t < b for a, b in self.link_losses)
        if down != self._link_was_down:
            self._link_was_down = down
            log.warning("SIMULATED MAVLINK LINK LOSS: vehicle %d %s link %s at sim t=%.2f s (dropped so far: %s)",
                        self.vehicle.system_id, self.name, "DOWN" if down else "back up", t, self.link_loss_dropped)
        return down

    # ------------------------------------------------------------------ asyncio plumbing
    def connection_made(self, transport) -> None:
        self.transport = transport

    def datagram_received(self, data: bytes, addr) -> None:
        if self.link_down():
            self.link_loss_dropped["received"] += 1
            return
        if addr != self.remote:
            log.info("vehicle %d %s link: partner now %s:%d", self.vehicle.system_id, self.name, addr[0], addr[1])
            self.remote = addr
        try:
            msgs = self.mav.parse_buffer(data) or []
        except mavlink.MAVError as e:
            log.debug("vehicle %d: bad MAVLink packet from %s: %s", self.vehicle.system_id, addr, e)
            return
        for msg in msgs:
            try:
                self.handle(msg)
            except Exception:  # a bad message must not stop the vehicle
                log.exception("vehicle %d: error handling %s", self.vehicle.system_id, msg.get_type())

    def error_received(self, exc) -> None:  # e.g. ICMP port unreachable: nobody listening yet
        log.debug("vehicle %d %s link: %s", self.vehicle.system_id, self.name, exc)

    def _sendto(self, buf: bytes) -> None:
        if self.link_down():
            self.link_loss_dropped["sent"] += 1
            return
        if self.transport is not None and not self.transport.is_closing():
            self.transport.sendto(buf, self.remote)

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()

    @property
    def local_port(self) -> int:
        return self.transport.get_extra_info("sockname")[1]

    # ------------------------------------------------------------------ streaming
    def tick(self, t_s: float) -> None:
        """Send whatever stream is due at ``t_s`` and any queued status texts."""
        v = self.vehicle
        for name, period in self.period_s.items():
            if period == math.inf:
                continue
            due = self._next_due[name]
            if t_s + 1e-4 >= due:
                self.send_stream(name)
                nd = due + period
                self._next_due[name] = nd if nd > t_s else t_s + period
        new = min(v.status_count - self._texts_sent, len(v.status_texts))
        self._texts_sent = v.status_count
        for sev, text in v.status_texts[len(v.status_texts) - new :] if new > 0 else ():
            self.mav.send(self.mav.statustext_encode(sev, text.encode()[:50]))

    def send_stream(self, name: str) -> bool:
        """Send one message of stream ``name`` now; False if it cannot be sent (e.g. no home yet)."""
        v, mav = self.vehicle, self.mav
        t_s = self.clock()
        t_ms = int(t_s * 1000) & 0xFFFFFFFF
        if name == "HEARTBEAT":
            status = M.MAV_STATE_ACTIVE if v.armed else M.MAV_STATE_STANDBY
            msg = mav.heartbeat_encode(
                M.MAV_TYPE_QUADROTOR,
                M.MAV_AUTOPILOT_PX4,
                heartbeat_base_mode(v.mode, v.armed),
                encode_custom_mode(v.mode.main_mode, v.mode.sub_mode),
                status,
                3,
            )
        elif name == "SYS_STATUS":
            health = SENSORS_PRESENT
            if not v.gps_ok:
                health &= ~(M.MAV_SYS_STATUS_SENSOR_GPS | M.MAV_SYS_STATUS_PREARM_CHECK)
            if not v.prearm_ok:  # battery critical, or disarmed in Offboard (until a mode change)
                health &= ~M.MAV_SYS_STATUS_PREARM_CHECK
            b = v.battery
            msg = mav.sys_status_encode(
                SENSORS_PRESENT,
                SENSORS_PRESENT,
                health,
                250,
                int(b.voltage_v * 1000),
                int(b.current_a * 100),
                int(round(b.remaining_pct)),
                0,
                0,
                0,
                0,
                0,
                0,
            )
        elif name == "BATTERY_STATUS":
            b = v.battery
            cells = [int(b.voltage_v / b.cfg.cells * 1000)] * b.cfg.cells + [65535] * (10 - b.cfg.cells)
            msg = mav.battery_status_encode(
                0,
                M.MAV_BATTERY_FUNCTION_ALL,
                M.MAV_BATTERY_TYPE_LIPO,
                32767,
                cells,
                int(b.current_a * 100),
                int(b.consumed_mah),
                -1,
                int(round(b.remaining_pct)),
            )
        elif name == "EXTENDED_SYS_STATE":
            msg = mav.extended_sys_state_encode(M.MAV_VTOL_STATE_UNDEFINED, v.landed_state)
        elif name == "ATTITUDE":
            r, p, y = euler_from_R(v.est_R_world_body)
            w = v.truth.angular_velocity_body_rad_s
            msg = mav.attitude_encode(t_ms, r, p, y, w[0], w[1], w[2])
        elif name == "ATTITUDE_QUATERNION":
            q = quat_wxyz_from_R(v.est_R_world_body)
            w = v.truth.angular_velocity_body_rad_s
            msg = mav.attitude_quaternion_encode(t_ms, q[0], q[1], q[2], q[3], w[0], w[1], w[2])
        elif name == "LOCAL_POSITION_NED":
            p, vel = v.est_local_position_ned_m, v.est_velocity_ned_m_s
            msg = mav.local_position_ned_encode(t_ms, p[0], p[1], p[2], vel[0], vel[1], vel[2])
        elif name == "GLOBAL_POSITION_INT":
            lat, lon, alt = v.geodetic(v.est_position_ned_m)
            home_d = v.home_ned_m[2] if v.home_ned_m is not None else v.spawn_ned_m[2]
            vel = v.est_velocity_ned_m_s
            hdg = int(round(math.degrees(v.est_yaw_rad) * 100)) % 36000
            msg = mav.global_position_int_encode(
                t_ms,
                int(round(lat * 1e7)),
                int(round(lon * 1e7)),
                int(round(alt * 1000)),
                int(round((home_d - v.est_position_ned_m[2]) * 1000)),
                int(round(vel[0] * 100)),
                int(round(vel[1] * 100)),
                int(round(vel[2] * 100)),
                hdg,
            )
        elif name == "GPS_RAW_INT":
            vel = v.est_velocity_ned_m_s
            if v.gps_ok:
                lat, lon, alt = v.geodetic(v.est_position_ned_m)
                fix, sats, eph = M.GPS_FIX_TYPE_3D_FIX, 14, 70
            else:
                lat = lon = alt = 0.0
                fix, sats, eph = M.GPS_FIX_TYPE_NO_FIX, 3, 9999
            gs = math.hypot(vel[0], vel[1])
            cog = int(round(math.degrees(math.atan2(vel[1], vel[0])) * 100)) % 36000 if gs > 0.2 else 65535
            msg = mav.gps_raw_int_encode(
                int(time.time() * 1e6),
                fix,
                int(round(lat * 1e7)),
                int(round(lon * 1e7)),
                int(round(alt * 1000)),
                eph,
                eph + 30,
                int(gs * 100),
                cog,
                sats,
                int(round(alt * 1000)),
                # h_acc / v_acc (mm): the estimator's position error grade (1 sigma), as a receiver reports it
                int(round(1000 * v.cfg.estimator.pos_bias_std_xy_m)) if v.gps_ok else 99000,
                int(round(1000 * v.cfg.estimator.pos_bias_std_z_m)) if v.gps_ok else 99000,
                150,
                0,
                0,
            )
        elif name == "HOME_POSITION":
            if v.home_ned_m is None:
                return False
            lat, lon, alt = v.geodetic(v.home_ned_m)
            hl = v.home_ned_m - v.local_origin_ned_m
            msg = mav.home_position_encode(
                int(round(lat * 1e7)),
                int(round(lon * 1e7)),
                int(round(alt * 1000)),
                hl[0],
                hl[1],
                hl[2],
                [1.0, 0.0, 0.0, 0.0],
                0.0,
                0.0,
                0.0,
                int(time.time() * 1e6),
            )
        elif name == "VFR_HUD":
            vel = v.est_velocity_ned_m_s
            _, _, alt = v.geodetic(v.est_position_ned_m)
            thr = int(min(100, 50 * v.truth.thrust_m_s2 / GRAVITY_M_S2)) if v.armed else 0
            hdg = int(round(math.degrees(v.est_yaw_rad))) % 360
            gs = math.hypot(vel[0], vel[1])
            msg = mav.vfr_hud_encode(gs, gs, hdg, thr, alt, -vel[2])
        elif name == "SYSTEM_TIME":
            msg = mav.system_time_encode(int(time.time() * 1e6), t_ms)
        elif name == "ODOMETRY":
            p = v.est_local_position_ned_m
            R = v.est_R_world_body
            vb = R.T @ v.est_velocity_ned_m_s  # body-frame velocity, as PX4 sends it
            w = v.truth.angular_velocity_body_rad_s
            nan21 = [math.nan] * 21
            msg = mav.odometry_encode(
                int(time.time() * 1e6), M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_BODY_FRD, p[0], p[1], p[2],
                list(quat_wxyz_from_R(R)), vb[0], vb[1], vb[2], w[0], w[1], w[2], nan21, nan21, 0,
                M.MAV_ESTIMATOR_TYPE_GPS_INS, 100,
            )  # fmt: skip
        elif name == "GPS_GLOBAL_ORIGIN":
            if not v.gps_ok:
                return False
            lat, lon, alt = v.geodetic(v.local_origin_ned_m)
            msg = mav.gps_global_origin_encode(
                int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)), int(time.time() * 1e6)
            )
        elif name == "GIMBAL_DEVICE_ATTITUDE_STATUS":
            g = v.gimbal
            if g is None:
                return False
            # the true gimbal angles (its encoders); yaw in the vehicle frame, roll and pitch to the horizon
            msg = mav.gimbal_device_attitude_status_encode(
                0, 0, t_ms, self._gimbal_flags(), list(quat_wxyz_from_pitch_yaw(g.pitch_rad, g.yaw_rad)),
                0.0, g.pitch_rate_rad_s, g.yaw_rate_rad_s, 0, v.est_yaw_rad, math.nan, GIMBAL_DEVICE_ID,
            )  # fmt: skip
        elif name == "GIMBAL_MANAGER_STATUS":
            g = v.gimbal
            if g is None:
                return False
            msg = mav.gimbal_manager_status_encode(t_ms, self._gimbal_flags(), GIMBAL_DEVICE_ID, *g.primary_control,
                                                   *g.secondary_control)
        else:
            return False
        mav.send(msg)
        self.sent_counts[name] += 1
        return True

    def _gimbal_flags(self) -> int:
        """GIMBAL_DEVICE_FLAGS (= the manager's flags): roll and pitch stabilised, yaw follow or lock."""
        lock = self.vehicle.gimbal is not None and self.vehicle.gimbal.yaw_lock
        return (M.GIMBAL_DEVICE_FLAGS_ROLL_LOCK | M.GIMBAL_DEVICE_FLAGS_PITCH_LOCK
                | M.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME | (M.GIMBAL_DEVICE_FLAGS_YAW_LOCK if lock else 0))

    # ------------------------------------------------------------------ receiving
    def handle(self, msg) -> None:
        """Act on one decoded message (public so tests can feed messages without sockets)."""
        t = msg.get_type()
        self.received_counts[t] = self.received_counts.get(t, 0) + 1
        v = self.vehicle
        if t == "BAD_DATA":
            return
        target_sys = getattr(msg, "target_system", None)
        if target_sys not in (None, 0, v.system_id):
            return
        target_comp = getattr(msg, "target_component", None)
        handler = getattr(self, "_on_" + t, None)
        if handler is None:
            return
        if t.startswith("COMMAND") and target_comp not in (0, AUTOPILOT_COMPONENT_ID):
            return
        handler(msg)

    def _ack(self, msg, command: int, result: int) -> None:
        self.mav.send(self.mav.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))

    def _on_COMMAND_LONG(self, msg) -> None:
        p = [msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7]
        self._command(msg, msg.command, p, frame=None)

    def _on_COMMAND_INT(self, msg) -> None:
        p = [msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z]
        self._command(msg, msg.command, p, frame=msg.frame)

    def _command(self, msg, cmd: int, p: list[float], frame: int | None) -> None:
        v = self.vehicle
        after = None  # message to send after the ACK
        if cmd == M.MAV_CMD_COMPONENT_ARM_DISARM:
            res = v.cmd_arm(p[0] > 0.5, force=abs(p[1] - ap.FORCE_MAGIC) < 0.5)
        elif cmd == M.MAV_CMD_NAV_TAKEOFF:
            res = v.cmd_takeoff(p[6] if frame is None else (p[6] if math.isfinite(p[6]) else math.nan))
        elif cmd == M.MAV_CMD_NAV_LAND:
            res = v.cmd_land()
        elif cmd == M.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            res = v.cmd_return()
        elif cmd == M.MAV_CMD_NAV_LOITER_UNLIM:
            res = v.cmd_hold()
        elif cmd == M.MAV_CMD_DO_SET_MODE:
            res = v.cmd_set_mode(p[0], p[1], p[2])
        elif cmd == M.MAV_CMD_DO_REPOSITION:
            res = self._reposition(p, frame)
        elif cmd == M.MAV_CMD_DO_CHANGE_SPEED:
            res = v.cmd_change_speed(p[1])
        elif cmd == M.MAV_CMD_SET_MESSAGE_INTERVAL:
            res = self._set_interval(int(p[0]), p[1])
        elif cmd == M.MAV_CMD_GET_MESSAGE_INTERVAL:
            name = MSGID_TO_STREAM.get(int(p[0]))
            if name is None:
                res = ap.UNSUPPORTED
            else:
                res = ap.ACCEPTED
                period = self.period_s[name]
                interval_us = -1 if period == math.inf else int(period * 1e6)
                reply = self.mav.message_interval_encode(int(p[0]), interval_us)

                def after():
                    self.mav.send(reply)
        elif cmd == M.MAV_CMD_REQUEST_MESSAGE:
            res, after = self._request_message(int(p[0]))
        elif cmd == M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            res, after = self._request_message(M.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        elif cmd == M.MAV_CMD_GET_HOME_POSITION:
            res, after = self._request_message(M.MAVLINK_MSG_ID_HOME_POSITION)
        elif cmd == M.MAV_CMD_DO_SET_HOME:
            res = self._set_home(p, frame)
        elif cmd == M.MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE:
            res = self._gimbal_configure(msg, p)
            if res == ap.ACCEPTED:
                def after():
                    self.send_stream("GIMBAL_MANAGER_STATUS")
        elif cmd == M.MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW:
            # param5 = GIMBAL_MANAGER_FLAGS (COMMAND_INT: x), param7 = gimbal device id (COMMAND_INT: z)
            res = self._gimbal_pitchyaw(msg, int(p[4]) if math.isfinite(p[4]) else 0, math.radians(p[0]),
                                        math.radians(p[1]), math.radians(p[2]), math.radians(p[3]), p[6])
        else:
            res = ap.UNSUPPORTED
            log.debug("vehicle %d: unsupported command %d", v.system_id, cmd)
        log.debug("vehicle %d %s link: command %d %s -> result %d", v.system_id, self.name, cmd, p, res)
        self.command_log.append((cmd, res))
        self._ack(msg, cmd, res)
        if after is not None:
            after()

    def _world_from_global(self, lat_deg: float, lon_deg: float, alt_m: float, frame: int | None) -> np.ndarray:
        """World NED of a (lat, lon, alt) in a MAV_FRAME; NaN components stay NaN."""
        o = self.vehicle.cfg.origin
        v = self.vehicle
        if frame in (M.MAV_FRAME_GLOBAL_RELATIVE_ALT, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT):
            home_alt = v.geodetic(v.home_ned_m)[2] if v.home_ned_m is not None else o.alt_m
            alt_m = home_alt + alt_m
        elif frame in (M.MAV_FRAME_GLOBAL_TERRAIN_ALT, M.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT):
            alt_m = o.alt_m - v.dyn.ground_down_m + alt_m  # flat ground
        if math.isfinite(lat_deg) and math.isfinite(lon_deg):
            ned = geodetic_to_ned(
                lat_deg, lon_deg, alt_m if math.isfinite(alt_m) else o.alt_m, o.lat_deg, o.lon_deg, o.alt_m
            )
        else:
            ned = np.array([math.nan, math.nan, o.alt_m - alt_m if math.isfinite(alt_m) else math.nan])
        if not math.isfinite(alt_m):
            ned[2] = math.nan
        return np.asarray(ned, dtype=float)

    def _reposition(self, p: list[float], frame: int | None) -> int:
        if frame is None:  # COMMAND_LONG: degrees
            lat, lon = p[4], p[5]
        else:  # COMMAND_INT: degE7 in x/y (0 = not set)
            lat = p[4] * 1e-7 if p[4] != 0 else math.nan
            lon = p[5] * 1e-7 if p[5] != 0 else math.nan
        world = self._world_from_global(lat, lon, p[6], frame if frame is not None else M.MAV_FRAME_GLOBAL)
        speed = p[0] if p[0] > 0 else math.nan
        return self.vehicle.cmd_reposition(world, yaw_rad=p[3], speed_m_s=speed)

    def _set_home(self, p: list[float], frame: int | None) -> int:
        v = self.vehicle
        if p[0] > 0.5:
            v.home_ned_m = v.est_position_ned_m.copy()
            return ap.ACCEPTED
        lat, lon = (p[4], p[5]) if frame is None else (p[4] * 1e-7, p[5] * 1e-7)
        world = self._world_from_global(lat, lon, p[6], M.MAV_FRAME_GLOBAL)
        if not np.all(np.isfinite(world)):
            return ap.DENIED
        v.home_ned_m = world
        return ap.ACCEPTED

    def _set_interval(self, msg_id: int, interval_us: float) -> int:
        name = MSGID_TO_STREAM.get(msg_id)
        if name is None:
            return ap.UNSUPPORTED
        if interval_us < -0.5:
            self.period_s[name] = math.inf
        elif interval_us < 0.5:
            self.period_s[name] = self.default_period_s[name]
        else:
            self.period_s[name] = max(interval_us * 1e-6, 0.004)  # at most 250 Hz
        self._next_due[name] = self.clock()
        log.debug("vehicle %d %s link: %s every %.3f s", self.vehicle.system_id, self.name, name, self.period_s[name])
        return ap.ACCEPTED

    def _request_message(self, msg_id: int):
        """(MAV_RESULT, function sending the message after the ACK)."""
        if msg_id == M.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return ap.ACCEPTED, self._send_autopilot_version
        if msg_id in (M.MAVLINK_MSG_ID_GIMBAL_MANAGER_INFORMATION, M.MAVLINK_MSG_ID_GIMBAL_DEVICE_INFORMATION):
            if self.vehicle.gimbal is None:
                return ap.UNSUPPORTED, None
            return ap.ACCEPTED, lambda: self._send_gimbal_information(msg_id)
        name = MSGID_TO_STREAM.get(msg_id)
        if name is None or (name in GIMBAL_STREAMS and self.vehicle.gimbal is None):
            return ap.UNSUPPORTED, None
        if (name == "HOME_POSITION" and self.vehicle.home_ned_m is None) or (
            name == "GPS_GLOBAL_ORIGIN" and not self.vehicle.gps_ok
        ):
            return ap.TEMPORARILY_REJECTED, None
        return ap.ACCEPTED, lambda: self.send_stream(name)

    # ------------------------------------------------------------------ gimbal protocol v2 (autopilot = manager)
    def _send_gimbal_information(self, msg_id: int) -> None:
        g = self.vehicle.gimbal
        t_ms = int(self.clock() * 1000) & 0xFFFFFFFF
        (p0, p1), (y0, y1) = g.pitch_limits_rad, g.yaw_limits_rad
        if msg_id == M.MAVLINK_MSG_ID_GIMBAL_MANAGER_INFORMATION:
            self.mav.send(self.mav.gimbal_manager_information_encode(t_ms, GIMBAL_CAP_FLAGS, GIMBAL_DEVICE_ID,
                                                                     0.0, 0.0, p0, p1, y0, y1))
        else:
            self.mav.send(self.mav.gimbal_device_information_encode(
                t_ms, g.cfg.vendor_name.encode()[:32], g.cfg.model_name.encode()[:32], b"", 1, 1,
                0x534B59470000 + self.vehicle.system_id, GIMBAL_CAP_FLAGS & 0xFFFF, 0, 0.0, 0.0, p0, p1, y0, y1,
                GIMBAL_DEVICE_ID,
            ))  # fmt: skip

    @staticmethod
    def _for_our_gimbal(device_id: float) -> bool:
        """A gimbal device id addresses this vehicle's gimbal: 0 (all) or :data:`GIMBAL_DEVICE_ID`."""
        return math.isfinite(device_id) and int(round(device_id)) in (0, GIMBAL_DEVICE_ID)

    def _gimbal_configure(self, msg, p: list[float]) -> int:
        """MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE: param1/2 primary, param3/4 secondary control (sysid, compid;
        -1 leave, -2 the sender, -3 release if the sender holds it), param7 gimbal device id."""
        g = self.vehicle.gimbal
        if g is None:
            return ap.UNSUPPORTED
        if not self._for_our_gimbal(p[6]):
            return ap.DENIED
        sender = (msg.get_srcSystem(), msg.get_srcComponent())

        def assign(current: tuple[int, int], sysid: float, compid: float) -> tuple[int, int]:
            if not (math.isfinite(sysid) and math.isfinite(compid)) or sysid == -1:
                return current
            if sysid == -2:
                return sender
            if sysid == -3:
                return (0, 0) if current == sender else current
            return int(sysid), int(compid)

        g.primary_control = assign(g.primary_control, p[0], p[1])
        g.secondary_control = assign(g.secondary_control, p[2], p[3])
        log.info("vehicle %d: gimbal control primary %s secondary %s", self.vehicle.system_id, g.primary_control,
                 g.secondary_control)
        return ap.ACCEPTED

    def _gimbal_pitchyaw(self, msg, flags: int, pitch_rad: float, yaw_rad: float, pitch_rate_rad_s: float,
                         yaw_rate_rad_s: float, device_id: float) -> int:
        """Angles (NaN: not set) or, when both angles are NaN, rates. Yaw is relative to the heading unless
        ``flags`` has YAW_LOCK or YAW_IN_EARTH_FRAME (then relative to north). Only the controllers in charge
        (primary or secondary) may command; with nobody in charge anyone may (as after boot)."""
        v, g = self.vehicle, self.vehicle.gimbal
        if g is None:
            return ap.UNSUPPORTED
        if not self._for_our_gimbal(device_id):
            return ap.DENIED
        sender = (msg.get_srcSystem(), msg.get_srcComponent())
        if g.primary_control != (0, 0) and sender not in (g.primary_control, g.secondary_control):
            log.info("vehicle %d: gimbal command from %s denied: %s is in control", v.system_id, sender,
                     g.primary_control)
            return ap.DENIED
        lock = bool(flags & (M.GIMBAL_MANAGER_FLAGS_YAW_LOCK | M.GIMBAL_MANAGER_FLAGS_YAW_IN_EARTH_FRAME))
        if math.isfinite(pitch_rad) or math.isfinite(yaw_rad):
            g.set_angles(pitch_rad, yaw_rad, lock, v.est_yaw_rad)
        elif math.isfinite(pitch_rate_rad_s) or math.isfinite(yaw_rate_rad_s):
            g.set_rates(pitch_rate_rad_s, yaw_rate_rad_s, lock, v.est_yaw_rad)
        else:
            return ap.DENIED
        log.debug("vehicle %d: gimbal -> pitch %.1f yaw %.1f deg (%s)", v.system_id, math.degrees(pitch_rad),
                  math.degrees(yaw_rad), "lock" if lock else "follow")
        return ap.ACCEPTED

    def _on_GIMBAL_MANAGER_SET_ATTITUDE(self, msg) -> None:
        if msg.target_component not in (0, AUTOPILOT_COMPONENT_ID):
            return
        q = list(msg.q)
        if all(math.isfinite(x) for x in q) and any(q):
            _, pitch, yaw = euler_from_R(R_from_quat_wxyz(q))
        else:
            pitch = yaw = math.nan
        self._gimbal_pitchyaw(msg, msg.flags, pitch, yaw, msg.angular_velocity_y, msg.angular_velocity_z,
                              msg.gimbal_device_id)

    def _on_GIMBAL_MANAGER_SET_PITCHYAW(self, msg) -> None:
        if msg.target_component not in (0, AUTOPILOT_COMPONENT_ID):
            return
        self._gimbal_pitchyaw(msg, msg.flags, msg.pitch, msg.yaw, msg.pitch_rate, msg.yaw_rate, msg.gimbal_device_id)

    def _send_autopilot_version(self) -> None:
        sid = self.vehicle.system_id
        self.mav.send(
            self.mav.autopilot_version_encode(
                CAPABILITIES,
                PX4_VERSION,
                0,
                0,
                0,
                [0] * 8,
                [0] * 8,
                [0] * 8,
                0,  # vendor id (PX4 SITL: none)
                0,  # product id
                0x534B590000000000 + sid,
            )
        )

    def _on_SET_POSITION_TARGET_LOCAL_NED(self, msg) -> None:
        mask, v = msg.type_mask, self.vehicle
        pos = np.array([msg.x, msg.y, msg.z], dtype=float)
        vel = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
        acc = np.array([msg.afx, msg.afy, msg.afz], dtype=float)
        for k in range(3):
            if mask & (1 << k):
                pos[k] = math.nan
            if mask & (1 << (3 + k)):
                vel[k] = math.nan
            if mask & (1 << (6 + k)):
                acc[k] = math.nan
        yaw = math.nan if mask & (1 << 10) else msg.yaw
        yaw_rate = math.nan if mask & (1 << 11) else msg.yaw_rate
        frame = msg.coordinate_frame
        if frame in (M.MAV_FRAME_BODY_NED, M.MAV_FRAME_BODY_FRD, M.MAV_FRAME_BODY_OFFSET_NED):
            # velocities/accelerations in a yaw-aligned body frame; positions as offsets from here
            c, s = math.cos(v.est_yaw_rad), math.sin(v.est_yaw_rad)
            Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            vel = Rz @ np.nan_to_num(vel, nan=0.0) if not np.all(np.isnan(vel)) else vel
            acc = Rz @ np.nan_to_num(acc, nan=0.0) if not np.all(np.isnan(acc)) else acc
            if not np.all(np.isnan(pos)):
                pos = v.est_local_position_ned_m + Rz @ np.nan_to_num(pos, nan=0.0)
            if frame == M.MAV_FRAME_BODY_OFFSET_NED or frame == M.MAV_FRAME_BODY_FRD:
                if not math.isnan(yaw):
                    yaw = v.est_yaw_rad + yaw
        elif frame == M.MAV_FRAME_LOCAL_OFFSET_NED:
            if not np.all(np.isnan(pos)):
                pos = v.est_local_position_ned_m + np.nan_to_num(pos, nan=0.0)
        elif frame not in (M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_LOCAL_FRD):
            return
        v.set_offboard_setpoint(
            TrajectorySetpoint(position_ned_m=pos, velocity_ned_m_s=vel, accel_ned_m_s2=acc, yaw_rad=yaw,
                               yaw_rate_rad_s=yaw_rate)
        )

    def _on_SET_POSITION_TARGET_GLOBAL_INT(self, msg) -> None:
        v, mask = self.vehicle, msg.type_mask
        lat = math.nan if mask & 1 else msg.lat_int * 1e-7
        lon = math.nan if mask & 2 else msg.lon_int * 1e-7
        alt = math.nan if mask & 4 else msg.alt
        world = self._world_from_global(lat, lon, alt, msg.coordinate_frame)
        vel = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
        for k in range(3):
            if mask & (1 << (3 + k)):
                vel[k] = math.nan
        yaw = math.nan if mask & (1 << 10) else msg.yaw
        yaw_rate = math.nan if mask & (1 << 11) else msg.yaw_rate
        v.set_offboard_setpoint(
            TrajectorySetpoint(
                position_ned_m=world - v.local_origin_ned_m, velocity_ned_m_s=vel, yaw_rad=yaw, yaw_rate_rad_s=yaw_rate
            )
        )

    def _on_SET_ATTITUDE_TARGET(self, msg) -> None:
        v, mask = self.vehicle, msg.type_mask
        yaw_rate = math.nan if mask & 4 else msg.body_yaw_rate
        thrust = 0.5 if mask & 64 else msg.thrust  # normalised; hover ~ 0.5 (PX4 MPC_THR_HOVER)
        if mask & 128:  # attitude ignored (rates only): keep level, apply the yaw rate
            R = np.eye(3)
            yaw = math.nan
        else:
            R = R_from_quat_wxyz(msg.q)
            yaw = math.nan if not math.isnan(yaw_rate) and yaw_rate != 0.0 else yaw_from_R(R)
        sp = TrajectorySetpoint(yaw_rad=yaw, yaw_rate_rad_s=yaw_rate)
        sp.body_z_cmd = R[:, 2].copy()
        sp.thrust_m_s2 = float(thrust) / 0.5 * GRAVITY_M_S2
        v.set_offboard_setpoint(sp)

    def _send_param(self, p, index: int) -> None:
        self.mav.send(
            self.mav.param_value_encode(
                p.name.encode(), encode_param_value(p.value, p.type), p.type, len(self.vehicle.params), index
            )
        )

    def _on_PARAM_REQUEST_LIST(self, msg) -> None:
        for i, p in enumerate(self.vehicle.params.all()):
            self._send_param(p, i)

    def _on_PARAM_REQUEST_READ(self, msg) -> None:
        store = self.vehicle.params
        if msg.param_index >= 0:
            p, idx = store.by_index(msg.param_index), msg.param_index
        else:
            name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(errors="ignore")
            name = name.rstrip("\x00")
            p = store.get(name)
            idx = store.index_of(name) if p is not None else -1
        if p is not None:
            self._send_param(p, idx)

    def _on_PARAM_SET(self, msg) -> None:
        store = self.vehicle.params
        name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(errors="ignore")
        name = name.rstrip("\x00")
        p = store.get(name)
        if p is None:
            log.info("vehicle %d: PARAM_SET of unknown parameter %s ignored", self.vehicle.system_id, name)
            return
        store.set(name, decode_param_value(msg.param_value, p.type))
        self._send_param(p, store.index_of(name))

    def _on_MISSION_REQUEST_LIST(self, msg) -> None:
        self.mav.send(self.mav.mission_count_encode(msg.get_srcSystem(), msg.get_srcComponent(), 0, msg.mission_type))

    def _on_MISSION_CLEAR_ALL(self, msg) -> None:
        self.mav.send(
            self.mav.mission_ack_encode(
                msg.get_srcSystem(), msg.get_srcComponent(), M.MAV_MISSION_ACCEPTED, msg.mission_type
            )
        )

    def _on_MISSION_COUNT(self, msg) -> None:
        self.mav.send(
            self.mav.mission_ack_encode(
                msg.get_srcSystem(), msg.get_srcComponent(), M.MAV_MISSION_UNSUPPORTED, msg.mission_type
            )
        )

    def _on_PING(self, msg) -> None:
        if msg.target_system == 0:  # a ping request: answer it (PX4 does)
            self.mav.send(self.mav.ping_encode(msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent()))

    def _on_TIMESYNC(self, msg) -> None:
        if msg.tc1 == 0:
            self.mav.send(self.mav.timesync_encode(time.monotonic_ns(), msg.ts1))
