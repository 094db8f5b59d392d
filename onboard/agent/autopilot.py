"""Thin MAVSDK 4 adapter: the agent's only door to the autopilot (PX4 or the built-in simulator).

It connects as a MAVLink companion computer, asks for telemetry at the recording rate, keeps the latest
telemetry of every stream as one typed record (``telemetry``: :class:`onboard.agent.telemetry.Telemetry`) and
calls ``on_state(VehicleState)`` for each position/velocity sample (the autopilot's own estimate, what the
recorder keeps), and turns the agent's intents into MAVSDK calls
(arm, takeoff, offboard setpoints, land, return, hold, gimbal angles). No flight logic lives here.

Gimbal (MAVLink gimbal protocol v2 through MAVSDK's gimbal plugin): the plugin's gimbal list is polled until a
gimbal appears (``System.has_gimbal()`` is not used: it only sees a MAVLink gimbal *component*, not a gimbal
that the autopilot manages, as PX4 does for most gimbals and the built-in simulator does); the agent then takes
primary control and subscribes to its attitude: each report goes into ``telemetry`` and, as a
:class:`shared_msgs.GimbalAttitude`, to ``on_gimbal`` (the agent publishes and records it).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import time
from typing import Callable

import numpy as np

from shared_msgs import GimbalAttitude, VehicleState, now_ns
from skycap.errors import SkycapError
from skycap.frames import geodetic_to_ned

from onboard.agent.gimbal import BootClock, attitude_message
from onboard.agent.telemetry import LANDED_STATES, Telemetry
from onboard.setpoint import Setpoint

log = logging.getLogger(__name__)

__all__ = ["AutopilotError", "MavsdkAutopilot"]


class AutopilotError(SkycapError):
    """The autopilot could not be reached or refused an action."""


class MavsdkAutopilot:
    """One autopilot over MAVSDK (asyncio API of the ``mavsdk`` 4.x package).

    ``on_state`` is called on the event loop with a :class:`VehicleState` for every
    ``position_velocity_ned`` sample (``telemetry_hz``), combined with the latest attitude, battery,
    GPS, mode, armed and landed state.
    """

    def __init__(self, drone_id: str, on_state: Callable[[VehicleState], None] | None = None,
                 origin: tuple[float, float, float] = (47.397742, 8.545594, 488.0), offset_samples: int = 25):
        self.drone_id = drone_id
        #: geodetic origin (lat_deg, lon_deg, alt_m) of the world NED frame
        self.origin = tuple(float(x) for x in origin)
        #: world = local + offset (NED metres); estimated from global vs local position on the ground
        self.local_to_world_ned_m: np.ndarray | None = None
        self._offset_acc: list[np.ndarray] = []
        self._offset_samples = int(offset_samples)
        self.on_state = on_state
        self._mavsdk = None
        self._system = None
        self._tasks: list[asyncio.Task] = []
        #: the latest of every telemetry stream (replaced, never changed in place, on each sample)
        self.telemetry = Telemetry()
        self.last_state: VehicleState | None = None
        self._seq = 0
        self.offboard_active = False
        self.offboard_since_s = 0.0
        #: called with every gimbal report (a :class:`GimbalAttitude`) on the event loop
        self.on_gimbal: Callable[[GimbalAttitude], None] | None = None
        self._gimbal = None
        self._gimbal_id: int | None = None
        self._gimbal_warned = False
        self._gimbal_seq = 0
        self._gimbal_clock = BootClock()
        #: seconds the gimbal list is polled before "no gimbal" is logged (it keeps being polled)
        self.gimbal_discovery_s = 10.0

    # --- connection ----------------------------------------------------------------------------------
    async def connect(self, url: str, timeout_s: float = 30.0) -> None:
        """Open ``url`` (e.g. ``udpin://0.0.0.0:14540``) as a MAVLink companion computer and wait for an autopilot."""
        from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
        from mavsdk.asyncio.plugins.action import ActionAsync
        from mavsdk.asyncio.plugins.offboard import OffboardAsync
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

        self._mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER))
        try:
            await self._mavsdk.add_any_connection(url)
        except Exception as e:
            raise AutopilotError(f"cannot open MAVLink connection {url!r}: {e}; check the URL and that the port is free") from e
        log.info("%s: waiting for an autopilot on %s (up to %.0f s)", self.drone_id, url, timeout_s)
        system = await self._mavsdk.first_autopilot(timeout_s=timeout_s)
        if system is None:
            raise AutopilotError(
                f"no autopilot heartbeat on {url} within {timeout_s:.0f} s; is the simulator/PX4 running and "
                f"sending to this port?")
        self._system = system
        self.sysid = await system.get_system_id()
        self.action = ActionAsync(system)
        self.offboard = OffboardAsync(system)
        self.tel = TelemetryAsync(system)
        log.info("%s: connected to autopilot sysid %d", self.drone_id, self.sysid)

    async def start_telemetry(self, rate_hz: float = 50.0) -> None:
        """Ask for ``rate_hz`` position/velocity and attitude, and start the subscriptions."""
        tel = self.tel
        for name in ("set_rate_position_velocity_ned", "set_rate_attitude_quaternion", "set_rate_position"):
            try:
                await getattr(tel, name)(rate_hz)
            except Exception as e:  # PX4 may refuse a rate; keep its default and say so
                log.warning("%s: %s(%s) failed: %s", self.drone_id, name, rate_hz, e)
        for name in ("set_rate_battery", "set_rate_in_air", "set_rate_landed_state"):
            try:
                await getattr(tel, name)(2.0 if name == "set_rate_battery" else 5.0)
            except Exception as e:
                log.debug("%s: %s failed: %s", self.drone_id, name, e)

        def put(**fields) -> None:
            self.telemetry = dataclasses.replace(self.telemetry, **fields)

        def q(v):
            put(q_world_body_wxyz=(v.w, v.x, v.y, v.z))

        def armed(v):
            put(armed=bool(v))

        def in_air(v):
            put(in_air=bool(v))

        def landed(v):
            put(landed_state=LANDED_STATES.get(int(v), "unknown"))

        def mode(v):
            put(flight_mode=v.name)

        def battery(v):
            if math.isfinite(v.remaining_percent):
                put(battery_remaining_frac=max(0.0, min(1.0, v.remaining_percent / 100.0)))
            if math.isfinite(v.voltage_v):
                put(battery_voltage_v=v.voltage_v)

        def position(v):
            put(latitude_deg=v.latitude_deg, longitude_deg=v.longitude_deg, altitude_amsl_m=v.absolute_altitude_m)

        def gps(v):
            put(gps_fix_type=int(v.fix_type), gps_num_satellites=int(v.num_satellites))

        def raw_gps(v):
            h, vv = float(v.horizontal_uncertainty_m), float(v.vertical_uncertainty_m)
            put(horizontal_accuracy_m=h if math.isfinite(h) and 0 < h < 90 else math.nan,
                vertical_accuracy_m=vv if math.isfinite(vv) and 0 < vv < 90 else math.nan)

        def health(v):
            put(health_ok=bool(v.is_global_position_ok and v.is_home_position_ok and v.is_armable))

        subs = [
            (tel.subscribe_attitude_quaternion, q), (tel.subscribe_armed, armed), (tel.subscribe_in_air, in_air),
            (tel.subscribe_landed_state, landed), (tel.subscribe_flight_mode, mode), (tel.subscribe_battery, battery),
            (tel.subscribe_position, position), (tel.subscribe_gps_info, gps), (tel.subscribe_health, health),
            (tel.subscribe_raw_gps, raw_gps),
            (tel.subscribe_position_velocity_ned, self._on_posvel),
        ]
        for sub, cb in subs:
            self._tasks.append(asyncio.create_task(self._pump(sub, cb), name=f"tel:{sub.__name__}"))
        if self._system is not None:  # connected (not a test feeding the streams by hand)
            self._tasks.append(asyncio.create_task(self._discover_gimbal(), name="gimbal:discover"))

    async def _discover_gimbal(self) -> None:
        """Poll MAVSDK's gimbal list (1 Hz) until a gimbal appears; take primary control; stream its attitude."""
        from mavsdk.asyncio.plugins.gimbal import ControlMode, GimbalAsync

        try:
            self._gimbal = GimbalAsync(self._system)
            t0 = time.monotonic()
            while True:
                gimbals = (await self._gimbal.gimbal_list()).gimbals
                if gimbals:
                    break
                if not self._gimbal_warned and time.monotonic() - t0 > self.gimbal_discovery_s:
                    log.info("%s: no gimbal discovered in %.0f s: the camera keeps its mount pitch (still looking)",
                             self.drone_id, self.gimbal_discovery_s)
                    self._gimbal_warned = True
                await asyncio.sleep(1.0)
            g = gimbals[0]
            log.info("%s: gimbal %d discovered (%s %s, manager component %d, device %d)", self.drone_id, g.gimbal_id,
                     g.vendor_name, g.model_name, g.gimbal_manager_component_id, g.gimbal_device_id)
            try:
                await self._gimbal.take_control(g.gimbal_id, ControlMode.PRIMARY)
            except Exception as e:  # another component may hold it; commands may then be refused
                log.warning("%s: taking control of gimbal %d failed: %s", self.drone_id, g.gimbal_id, e)
            self._gimbal_id = g.gimbal_id
            await self._pump(self._gimbal.subscribe_attitude, self._on_gimbal_attitude)
        except asyncio.CancelledError:
            pass
        except Exception:
            log.exception("%s: gimbal discovery failed", self.drone_id)

    def _on_gimbal_attitude(self, a) -> None:
        if self._gimbal_id is not None and a.gimbal_id != self._gimbal_id:
            return
        T = self.telemetry
        t_ns = self._gimbal_clock.to_wall_ns(int(a.timestamp_us), now_ns())
        w, x, y, z = T.q_world_body_wxyz
        vehicle_yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        self._gimbal_seq += 1
        msg = attitude_message(self.drone_id, a, t_ns, self._gimbal_seq, vehicle_yaw)
        self.telemetry = dataclasses.replace(
            T, gimbal_id=msg.gimbal_id, gimbal_roll_rad=msg.roll_rad, gimbal_pitch_rad=msg.pitch_rad,
            gimbal_yaw_rad=msg.yaw_rad, gimbal_yaw_north_rad=msg.yaw_north_rad, gimbal_t_ns=t_ns)
        if self.on_gimbal is not None:
            self.on_gimbal(msg)

    async def _pump(self, subscribe, cb) -> None:
        try:
            async for v in subscribe():
                try:
                    cb(v)
                except Exception:
                    log.exception("%s: telemetry callback %s failed", self.drone_id, subscribe.__name__)
        except asyncio.CancelledError:
            pass

    def _on_posvel(self, v) -> None:
        p, vel = v.position, v.velocity
        if not (math.isfinite(p.north_m) and math.isfinite(p.east_m) and math.isfinite(p.down_m)):
            return
        T = self.telemetry
        local = np.array([p.north_m, p.east_m, p.down_m])
        if self.local_to_world_ned_m is None:
            # The autopilot's local frame is about its EKF origin: find where that is in the world frame
            # from the global position (same estimate), averaged over a few samples.
            if T.gps_fix_type < 3 or not math.isfinite(T.latitude_deg) or T.latitude_deg == 0.0:
                return
            world = geodetic_to_ned(T.latitude_deg, T.longitude_deg, T.altitude_amsl_m, *self.origin)
            self._offset_acc.append(world - local)
            if len(self._offset_acc) < self._offset_samples:
                return
            self.local_to_world_ned_m = np.mean(self._offset_acc, axis=0)
            log.info("%s: autopilot local origin at world NED %s m", self.drone_id,
                     np.round(self.local_to_world_ned_m, 2).tolist())
        w = local + self.local_to_world_ned_m
        self.telemetry = T = dataclasses.replace(T, position_ned_m=(float(w[0]), float(w[1]), float(w[2])),
                                                 velocity_ned_m_s=(vel.north_m_s, vel.east_m_s, vel.down_m_s))
        self._seq += 1
        st = T.vehicle_state(self.drone_id, now_ns(), self._seq)
        self.last_state = st
        if self.on_state is not None:
            self.on_state(st)

    async def wait_healthy(self, timeout_s: float) -> None:
        t_end = time.monotonic() + timeout_s
        while not (self.telemetry.health_ok and self.telemetry.position_ned_m is not None):
            if time.monotonic() > t_end:
                raise AutopilotError(
                    f"{self.drone_id}: autopilot not healthy after {timeout_s:.0f} s (needs GPS fix, home "
                    f"position, armable); check the vehicle's preflight checks")
            await asyncio.sleep(0.1)

    # --- actions -------------------------------------------------------------------------------------
    async def arm(self) -> None:
        await self._do("arm", self.action.arm())

    async def disarm(self) -> None:
        await self._do("disarm", self.action.disarm())

    async def takeoff(self, altitude_m: float) -> None:
        await self._do("set_takeoff_altitude", self.action.set_takeoff_altitude(float(altitude_m)))
        await self._do("takeoff", self.action.takeoff())

    async def land(self) -> None:
        await self._leave_offboard()
        await self._do("land", self.action.land())

    async def return_to_launch(self) -> None:
        await self._leave_offboard()
        await self._do("return_to_launch", self.action.return_to_launch())

    async def hold(self) -> None:
        await self._leave_offboard()
        await self._do("hold", self.action.hold())

    async def set_setpoint(self, sp: Setpoint) -> None:
        """Stream one position + velocity and acceleration feed-forward + yaw setpoint (world NED)."""
        from mavsdk.asyncio.plugins.offboard import AccelerationNed, PositionNedYaw, VelocityNedYaw

        if self.local_to_world_ned_m is None:
            raise AutopilotError(f"{self.drone_id}: no position fix yet, cannot place a world setpoint")
        yaw_deg = math.degrees(sp.yaw_rad)
        p = np.asarray(sp.position_ned_m) - self.local_to_world_ned_m  # world -> autopilot local
        v, a = sp.velocity_ned_m_s, sp.acceleration_ned_m_s2
        await self.offboard.set_position_velocity_acceleration_ned(
            PositionNedYaw(float(p[0]), float(p[1]), float(p[2]), yaw_deg),
            VelocityNedYaw(float(v[0]), float(v[1]), float(v[2]), yaw_deg),
            AccelerationNed(float(a[0]), float(a[1]), float(a[2])),
        )

    @property
    def has_gimbal(self) -> bool:
        """A gimbal was discovered (and control of it asked for)."""
        return self._gimbal_id is not None

    async def set_gimbal_pitch(self, pitch_rad: float) -> bool:
        """Point the camera gimbal (MAVLink gimbal protocol v2 via MAVSDK) to ``pitch_rad`` (negative = down),
        yaw following the vehicle (MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW; returns when the autopilot acknowledged it,
        raises :class:`AutopilotError` when it refused). False when no gimbal has been discovered (yet): the
        camera then keeps its mount's pitch."""
        if self._gimbal_id is None:
            return False
        from mavsdk.asyncio.plugins.gimbal import GimbalMode, SendMode

        await self._do("gimbal set_angles", self._gimbal.set_angles(
            self._gimbal_id, 0.0, math.degrees(pitch_rad), 0.0, GimbalMode.YAW_FOLLOW, SendMode.ONCE))
        return True

    async def start_offboard(self) -> None:
        """Switch to offboard; a setpoint must have been streamed first (PX4 requirement)."""
        await self._do("offboard start", self.offboard.start())
        self.offboard_active = True
        self.offboard_since_s = time.monotonic()

    async def _leave_offboard(self) -> None:
        self.offboard_active = False

    async def _do(self, what: str, coro) -> None:
        try:
            await coro
        except Exception as e:
            raise AutopilotError(f"{self.drone_id}: autopilot refused {what}: {e}") from e

    async def close(self) -> None:
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            try:
                await t
            except BaseException:
                pass
        self._tasks.clear()
        if self._gimbal is not None:
            self._gimbal.destroy()
            self._gimbal = None
        if self._mavsdk is not None:
            self._mavsdk.destroy()
            self._mavsdk = None
