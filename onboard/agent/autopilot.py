"""Thin MAVSDK 4 adapter: the agent's only door to the autopilot (PX4 or the built-in simulator).

It connects as a MAVLink companion computer, asks for telemetry at the recording rate, keeps the latest
telemetry of every stream as one typed record (``telemetry``: :class:`onboard.agent.telemetry.Telemetry`) and
calls ``on_state(VehicleState)`` for each position/velocity sample (the autopilot's own estimate, what the
recorder keeps), and turns the agent's intents into MAVSDK calls
(arm, takeoff, offboard setpoints, land, return, hold, gimbal angles). No flight logic lives here.

Frames: the autopilot's local NED frame is about its EKF origin. The adapter places that origin in the flight's
world frame: north / east about the configured geodetic ``origin`` from the same estimate's global position
(once, averaged over the first samples); down about the *ground the vehicle stands on*: the estimate's local down
is averaged while the vehicle reports itself on the ground and still, and that level is height 0 (re-measured
before every take-off, frozen in the air). Every height is then above the take-off point, whatever the ground's
altitude above mean sea level (PX4 SITL's SIH ground is 489.4 m, a configured origin 488 m: 1.4 m of error
otherwise) or a drift of the estimate between boot and take-off. MAVSDK's home and ``relative_altitude_m`` are
not used for this: measured on PX4 SITL, the home altitude MAVSDK reported jumped by up to 1.3 m in flight and
``relative_altitude_m`` disagreed with ``absolute_altitude_m`` minus home by up to 1.6 m, while the local down
stayed within 0.2 m of SIH's truth. An agent that starts in the air (a restart) takes the EKF origin's level
(PX4: where it booted, on the ground) until the vehicle next stands on the ground.

Modes: an acknowledged mode command is not trusted; :meth:`MavsdkAutopilot._confirm_mode` waits until the
vehicle *reports* the mode (PX4 reports it in its 1 Hz heartbeat), sends the command once more if it does not,
and raises :class:`AutopilotError` naming the mode it stayed in. Before arming, a vehicle that landed from
offboard (PX4 then keeps reporting OFFBOARD and is not armable) is put in HOLD first.

Parameters: :meth:`MavsdkAutopilot.apply_params` reads (and with ``set`` writes) the PX4 parameters the agent
relies on (:meth:`onboard.config.AutopilotConfig.params`) and logs each value it changed.

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
        #: the estimate's local down (m) of the ground the vehicle stands on (mean while on the ground and still)
        self.ground_local_down_m: float | None = None
        self._offset_samples = int(offset_samples)
        self.on_state = on_state
        self._mavsdk = None
        self._system = None
        self._tasks: list[asyncio.Task] = []
        #: the latest of every telemetry stream (replaced, never changed in place, on each sample)
        self.telemetry = Telemetry()
        #: every reported mode change (monotonic s, old, new), for the supervisor (a short excursion between two of
        #: its checks is not lost); it drops what it has read
        self.mode_changes: list[tuple[float, str, str]] = []
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
        from mavsdk.asyncio.plugins.param import ParamAsync
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
        self.param = ParamAsync(system)
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
            old = self.telemetry.flight_mode
            if v.name != old:
                log.info("%s: autopilot mode %s -> %s", self.drone_id, old, v.name)
                self.mode_changes.append((time.monotonic(), old, v.name))
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
            put(health_ok=bool(v.is_global_position_ok and v.is_home_position_ok and v.is_armable),
                global_position_ok=bool(v.is_global_position_ok), home_position_ok=bool(v.is_home_position_ok),
                armable=bool(v.is_armable))

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
        if T.landed_state == "on_ground" and not T.in_air and abs(vel.down_m_s) < 0.2:
            g = self.ground_local_down_m
            self.ground_local_down_m = float(local[2]) if g is None else g + 0.05 * (float(local[2]) - g)
        if self.local_to_world_ned_m is None:
            # The autopilot's local frame is about its EKF origin: find where that is in the world frame
            # from the global position (same estimate), averaged over a few samples
            if T.gps_fix_type < 3 or not math.isfinite(T.latitude_deg) or T.latitude_deg == 0.0:
                return
            world = geodetic_to_ned(T.latitude_deg, T.longitude_deg, T.altitude_amsl_m, *self.origin)
            self._offset_acc.append(world[:2] - local[:2])
            if len(self._offset_acc) < self._offset_samples:
                return
            ne = np.mean(self._offset_acc, axis=0)
            self.local_to_world_ned_m = np.array([ne[0], ne[1], 0.0])
            log.info("%s: autopilot local origin at world north/east %s m; heights above the ground %s", self.drone_id,
                     np.round(ne, 2).tolist(), "it stands on" if self.ground_local_down_m is not None else
                     "of the EKF origin until the vehicle stands on the ground (started in the air)")
        if self.ground_local_down_m is not None and not T.in_air:
            self.local_to_world_ned_m[2] = -self.ground_local_down_m
        w = local + self.local_to_world_ned_m
        self.telemetry = T = dataclasses.replace(T, position_ned_m=(float(w[0]), float(w[1]), float(w[2])),
                                                 velocity_ned_m_s=(vel.north_m_s, vel.east_m_s, vel.down_m_s))
        self._seq += 1
        st = T.vehicle_state(self.drone_id, now_ns(), self._seq)
        self.last_state = st
        if self.on_state is not None:
            self.on_state(st)

    async def wait_healthy(self, timeout_s: float) -> None:
        """Wait for the pre-arm conditions (global position, home, armable, a world position). A vehicle that
        :meth:`landed_in_offboard` and is not armable is put in HOLD first, once (:meth:`release_offboard`)."""
        t_end = time.monotonic() + timeout_s
        held = False
        while not (self.telemetry.health_ok and self.telemetry.position_ned_m is not None):
            T = self.telemetry
            if not held and not T.armable and self.landed_in_offboard():
                held = True
                await self.release_offboard()
            if time.monotonic() > t_end:
                why = [n for n, ok in (("global position", T.global_position_ok), ("home position", T.home_position_ok),
                                       ("armable", T.armable), ("world position", T.position_ned_m is not None)) if not ok]
                raise AutopilotError(
                    f"{self.drone_id}: autopilot not ready after {timeout_s:.0f} s: no {', no '.join(why)} (mode "
                    f"{T.flight_mode}); check the vehicle's preflight checks (GPS fix, home, arming checks)")
            await asyncio.sleep(0.1)

    def landed_in_offboard(self) -> bool:
        """On the ground, disarmed, and still reporting OFFBOARD (PX4 after landing from offboard: not armable
        until another mode is set)."""
        T = self.telemetry
        return (not T.in_air and not T.armed and T.flight_mode == "OFFBOARD" and T.landed_state == "on_ground"
                and not self.offboard_active)

    async def release_offboard(self) -> None:
        """Put a vehicle that :meth:`landed_in_offboard` in HOLD, so that it reports armable again."""
        log.info("%s: landed in OFFBOARD (PX4 is then not armable): setting HOLD", self.drone_id)
        await self._do("hold", self.action.hold())

    # --- parameters ----------------------------------------------------------------------------------
    async def apply_params(self, params: dict[str, float | int], write: bool = True) -> dict[str, tuple]:
        """Read each PX4 parameter of ``params`` (an ``int`` value: an INT32 parameter, else FLOAT) and, with
        ``write``, set the ones that differ. Returns ``{name: (old, new)}`` of what changed (``write``) or
        differs; logs every change, a missing parameter and a refusal (never raises: the agent flies on
        without them and says so)."""
        changed: dict[str, tuple] = {}
        for name, want in params.items():
            is_int = isinstance(want, int)
            try:
                old = await (self.param.get_param_int(name) if is_int else self.param.get_param_float(name))
            except Exception as e:
                log.warning("%s: autopilot parameter %s not readable (%s): cannot enforce %s=%s", self.drone_id, name,
                            e, name, want)
                continue
            same = old == want if is_int else math.isclose(old, want, rel_tol=1e-5, abs_tol=1e-4)
            if same:
                continue
            if not write:
                log.warning("%s: autopilot parameter %s=%s, the agent expects %s (autopilot.set_params=false: left)",
                            self.drone_id, name, old, want)
                changed[name] = (old, want)
                continue
            try:
                await (self.param.set_param_int(name, want) if is_int else self.param.set_param_float(name, float(want)))
            except Exception as e:
                log.warning("%s: setting autopilot parameter %s=%s failed: %s", self.drone_id, name, want, e)
                continue
            log.info("%s: autopilot parameter %s: %s -> %s", self.drone_id, name, old, want)
            changed[name] = (old, want)
        return changed

    # --- actions -------------------------------------------------------------------------------------
    async def arm(self) -> None:
        await self._do("arm", self.action.arm())

    async def disarm(self) -> None:
        await self._do("disarm", self.action.disarm())

    async def takeoff(self, altitude_m: float) -> None:
        """Take off to ``altitude_m`` above home; returns once the vehicle reports its take-off mode (or already
        holds in the air: a short climb may end before PX4's next heartbeat)."""
        await self._do("set_takeoff_altitude", self.action.set_takeoff_altitude(float(altitude_m)))
        await self._confirm_mode("takeoff", self.action.takeoff, lambda T: T.flight_mode == "TAKEOFF" or (
            T.flight_mode == "HOLD" and T.in_air))

    async def land(self) -> None:
        await self._leave_offboard()
        await self._confirm_mode("land", self.action.land, lambda T: T.flight_mode == "LAND" or not T.in_air)

    async def return_to_launch(self) -> None:
        await self._leave_offboard()
        await self._confirm_mode("return", self.action.return_to_launch,
                                 lambda T: T.flight_mode in ("RETURN_TO_LAUNCH", "LAND") or not T.in_air)

    async def hold(self) -> None:
        await self._leave_offboard()
        await self._confirm_mode("hold", self.action.hold, lambda T: T.flight_mode == "HOLD")

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
        """Switch to offboard (a setpoint must have been streamed first: PX4 requirement) and wait until the
        vehicle reports OFFBOARD."""
        await self._confirm_mode("offboard start", self.offboard.start, lambda T: T.flight_mode == "OFFBOARD")
        self.offboard_active = True
        self.offboard_since_s = time.monotonic()

    #: seconds :meth:`_confirm_mode` waits for the reported mode (per attempt; two attempts)
    mode_confirm_timeout_s = 3.0

    async def _confirm_mode(self, what: str, command, reached) -> None:
        """Send ``command()`` (a coroutine function) and wait until ``reached(telemetry)``; send it once more if
        the vehicle does not report it within ``mode_confirm_timeout_s``; raise :class:`AutopilotError` with the
        mode it stayed in otherwise. An acknowledgement alone is not trusted: PX4 acknowledges at once and shows
        its new mode up to 1 s later (heartbeat), or never when another mode overrides it (e.g. the HOLD that ends
        PX4's take-off)."""
        for attempt in (1, 2):
            await self._do(what, command())
            t_end = time.monotonic() + self.mode_confirm_timeout_s
            while time.monotonic() < t_end:
                if reached(self.telemetry):
                    if attempt > 1:
                        log.info("%s: %s confirmed on the second attempt", self.drone_id, what)
                    return
                await asyncio.sleep(0.05)
            log.warning("%s: %s acknowledged but the vehicle still reports %s after %.1f s%s", self.drone_id, what,
                        self.telemetry.flight_mode, self.mode_confirm_timeout_s,
                        ": sending it again" if attempt == 1 else "")
        raise AutopilotError(f"{self.drone_id}: {what} acknowledged but the vehicle stayed in "
                             f"{self.telemetry.flight_mode} (not confirmed after 2 attempts of "
                             f"{self.mode_confirm_timeout_s:.1f} s)")

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
