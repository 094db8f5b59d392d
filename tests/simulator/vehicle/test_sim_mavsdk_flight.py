"""The key integration test: unmodified MAVSDK 4 flies a simulated vehicle over UDP loopback.

The simulator runs in a background thread on free ports; MAVSDK listens with ``udpin://`` exactly as the
onboard agent does with PX4 SITL. Real time, so flights are kept short.
"""

from __future__ import annotations

import asyncio
import math
import time

import numpy as np
import pytest
from mavsdk.asyncio import Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.info import InfoAsync
from mavsdk.asyncio.plugins.offboard import OffboardAsync, OffboardError, OffboardResult, PositionNedYaw, VelocityNedYaw
from mavsdk.asyncio.plugins.param import ParamAsync
from mavsdk.asyncio.plugins.telemetry import FlightMode, LandedState, TelemetryAsync
from mavsdk.component_type import ComponentType
from sim_vehicle_helpers import sim_test_config

from skycap.frames import geodetic_to_ned

pytestmark = pytest.mark.timeout(180)


async def wait_for(pred, timeout_s: float, what: str, poll_s: float = 0.05):
    t0 = time.monotonic()
    while True:
        value = await pred()
        if value:
            return value
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        await asyncio.sleep(poll_s)


async def connect(port: int):
    mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    await mavsdk.add_any_connection(f"udpin://0.0.0.0:{port}")
    system = await mavsdk.first_autopilot(10.0)
    assert system is not None, "MAVSDK did not discover the simulated autopilot"
    return mavsdk, system


async def wait_healthy(tel: TelemetryAsync, timeout_s: float = 10.0):
    async def ok():
        h = await tel.health()
        return (
            h
            if (h.is_global_position_ok and h.is_home_position_ok and h.is_armable and h.is_local_position_ok)
            else None
        )

    return await wait_for(ok, timeout_s, "health ok (GPS, home, armable)")


class RateCounter:
    """Counts telemetry callbacks of one subscription in the background."""

    def __init__(self, agen):
        self.n = 0
        self.last = None
        self.task = asyncio.ensure_future(self._run(agen))

    async def _run(self, agen):
        async for x in agen:
            self.n += 1
            self.last = x

    def cancel(self):
        self.task.cancel()


def test_mavsdk_arm_takeoff_offboard_circle_land(sim_world_factory):
    cfg = sim_test_config()
    world = sim_world_factory(cfg)

    async def flight():
        mavsdk, system = await connect(cfg.ports.offboard_base)
        try:
            # --- what MAVSDK sees: a PX4 quadrotor
            assert int(await system.autopilot_type()) == 1  # mavsdk.Autopilot.PX4
            info = InfoAsync(system)
            version = await wait_for(lambda: _try(info.get_version), 5.0, "AUTOPILOT_VERSION")
            assert (version.flight_sw_major, version.flight_sw_minor) == (1, 15)
            tel, act, off, par = TelemetryAsync(system), ActionAsync(system), OffboardAsync(system), ParamAsync(system)
            await wait_healthy(tel)
            assert await tel.flight_mode() == FlightMode.HOLD
            assert await tel.landed_state() == LandedState.ON_GROUND
            assert not await tel.armed()
            pv_rate = RateCounter(tel.subscribe_position_velocity_ned())
            att_rate = RateCounter(tel.subscribe_attitude_quaternion())

            # --- params through the PARAM protocol
            await act.set_takeoff_altitude(5.0)
            assert await act.get_takeoff_altitude() == pytest.approx(5.0)
            await par.set_param_float("MPC_LAND_SPEED", 1.2)
            assert await par.get_param_float("MPC_LAND_SPEED") == pytest.approx(1.2)
            assert await par.get_param_int("MAV_SYS_ID") == 1

            # --- offboard refused by MAVSDK itself without a setpoint
            with pytest.raises(OffboardError) as e:
                await off.start()
            assert e.value.result == OffboardResult.NO_SETPOINT_SET

            # --- arm, take off to 5 m, PX4 switches to Hold when done
            await act.arm()
            assert await wait_for(tel.armed, 4.0, "armed")
            await act.takeoff()
            await wait_for(lambda: _mode_is(tel, FlightMode.TAKEOFF, FlightMode.HOLD), 4.0, "takeoff mode")

            async def at_takeoff_alt():
                pos = await tel.position()
                return pos.relative_altitude_m > 4.6 and await tel.flight_mode() == FlightMode.HOLD

            await wait_for(at_takeoff_alt, 12.0, "takeoff to 5 m, then Hold")
            # EXTENDED_SYS_STATE comes at 1 Hz (MAVSDK's action plugin sets that rate, on PX4 too)
            await wait_for(lambda: _landed_state_is(tel, LandedState.IN_AIR), 3.0, "landed state IN_AIR")
            truth = world.vehicles[0].truth.position_ned_m
            assert -truth[2] == pytest.approx(5.0, abs=1.3)  # the estimate's vertical bias is ~0.5 m

            # --- offboard: position setpoints, fly to a point
            start = (await tel.position_velocity_ned()).position
            await off.set_position_ned(PositionNedYaw(start.north_m, start.east_m, -5.0, 0.0))
            await off.start()
            assert await wait_for(lambda: _mode_is(tel, FlightMode.OFFBOARD), 4.0, "offboard mode")
            target = np.array([8.0, 4.0, -6.0])
            await off.set_position_ned(PositionNedYaw(*target, 90.0))

            async def near_target():
                p = (await tel.position_velocity_ned()).position
                return np.linalg.norm(np.array([p.north_m, p.east_m, p.down_m]) - target) < 0.6

            await wait_for(near_target, 12.0, "offboard flight to (8, 4, -6)")
            yaw = (await tel.attitude_euler()).yaw_deg
            assert yaw == pytest.approx(90.0, abs=8.0)

            # --- a quarter circle of radius 3 m around the point, streaming setpoints at 20 Hz
            centre = target - np.array([3.0, 0.0, 0.0])
            errors = []
            t0 = time.monotonic()
            while (t := time.monotonic() - t0) < 5.0:
                ang = (math.pi / 2) * t / 5.0
                sp = centre + np.array([3.0 * math.cos(ang), 3.0 * math.sin(ang), 0.0])
                await off.set_position_ned(PositionNedYaw(*sp, 90.0))
                p = (await tel.position_velocity_ned()).position
                errors.append(np.linalg.norm(np.array([p.north_m, p.east_m, p.down_m]) - sp))
                await asyncio.sleep(0.05)
            end = centre + np.array([0.0, 3.0, 0.0])

            async def near_end():
                p = (await tel.position_velocity_ned()).position
                return np.linalg.norm(np.array([p.north_m, p.east_m, p.down_m]) - end) < 0.6

            await wait_for(near_end, 5.0, "end of the arc")
            assert max(errors) < 2.5, f"tracking error along the arc too large: {max(errors):.2f} m"

            # --- stop offboard (MAVSDK switches to Hold), land, PX4 auto-disarms on the ground
            await off.stop()
            assert await wait_for(lambda: _mode_is(tel, FlightMode.HOLD), 4.0, "hold after offboard stop")
            await act.land()
            await wait_for(lambda: _mode_is(tel, FlightMode.LAND), 4.0, "land mode")
            await wait_for(lambda: _landed_state_is(tel, LandedState.ON_GROUND), 15.0, "touchdown")

            async def disarmed():
                return not await tel.armed()

            await wait_for(disarmed, 5.0, "auto-disarm after landing")
            p = (await tel.position_velocity_ned()).position
            assert math.hypot(p.north_m - end[0], p.east_m - end[1]) < 1.0  # landed where it stopped

            # --- telemetry rates seen through MAVSDK over the whole flight (lenient: shared 2-core CI)
            pv_rate.cancel()
            att_rate.cancel()
            return pv_rate.n, att_rate.n
        finally:
            mavsdk.destroy()

    t0 = time.monotonic()
    n_pv, n_att = asyncio.run(flight())
    dt = time.monotonic() - t0
    assert n_pv / dt > 25 and n_att / dt > 25, (
        f"telemetry too slow: {n_pv / dt:.0f} Hz position, {n_att / dt:.0f} Hz attitude"
    )
    truth = world.vehicles[0].truth
    assert truth.on_ground and not world.vehicles[0].armed
    # the truth stays within the estimator's bias of where MAVSDK saw it (world frame = local + spawn)
    assert np.linalg.norm(truth.position_ned_m[:2] - (world.vehicles[0].est_position_ned_m[:2])) < 4.0


def test_mavsdk_return_to_launch(sim_world_factory):
    cfg = sim_test_config(rtl_return_alt_m=4.0, takeoff_alt_m=3.0)
    cfg.vehicles.spawn_ne_m = [[2.0, -3.0]]
    world = sim_world_factory(cfg)

    async def flight():
        mavsdk, system = await connect(cfg.ports.offboard_base)
        try:
            tel, act = TelemetryAsync(system), ActionAsync(system)
            await wait_healthy(tel)
            home = await tel.home()
            await act.arm()
            await act.takeoff()

            async def up():
                return (await tel.position()).relative_altitude_m > 2.6

            await wait_for(up, 10.0, "takeoff")
            # the EKF origin (local frame origin) is the spawn point, as PX4's is where it got its first fix
            origin = await tel.get_gps_global_origin()
            o = cfg.origin
            np.testing.assert_allclose(
                geodetic_to_ned(
                    origin.latitude_deg, origin.longitude_deg, origin.altitude_m, o.lat_deg, o.lon_deg, o.alt_m
                ),
                [2.0, -3.0, 0.0],
                atol=0.02,
            )
            # offboard velocity setpoints
            off = OffboardAsync(system)
            await off.set_velocity_ned(VelocityNedYaw(0.0, 0.0, 0.0, 0.0))
            await off.start()
            await off.set_velocity_ned(VelocityNedYaw(0.0, 2.0, 0.0, 0.0))
            await asyncio.sleep(2.5)
            vel = await tel.velocity_ned()
            assert vel.east_m_s == pytest.approx(2.0, abs=0.3) and abs(vel.north_m_s) < 0.3 and abs(vel.down_m_s) < 0.3
            await off.stop()
            # goto a point 6 m north (DO_REPOSITION), then return
            pos = await tel.position()
            lat_north = pos.latitude_deg + math.degrees(6.0 / 6378137.0)
            await act.goto_location(lat_north, pos.longitude_deg, pos.absolute_altitude_m, 0.0)

            async def moved():
                p = (await tel.position()).latitude_deg
                return math.radians(p - pos.latitude_deg) * 6378137.0 > 5.0

            await wait_for(moved, 10.0, "goto 6 m north")
            await act.return_to_launch()
            assert await wait_for(lambda: _mode_is(tel, FlightMode.RETURN_TO_LAUNCH), 4.0, "RTL mode")
            await wait_for(lambda: _landed_state_is(tel, LandedState.ON_GROUND), 30.0, "landed at home")
            p = await tel.position()
            dn = math.radians(p.latitude_deg - home.latitude_deg) * 6378137.0
            de = (
                math.radians(p.longitude_deg - home.longitude_deg)
                * 6378137.0
                * math.cos(math.radians(home.latitude_deg))
            )
            assert math.hypot(dn, de) < 1.0, f"landed {math.hypot(dn, de):.2f} m from home"
        finally:
            mavsdk.destroy()

    asyncio.run(flight())
    truth = world.vehicles[0].truth.position_ned_m
    assert math.hypot(truth[0] - 2.0, truth[1] + 3.0) < 3.5  # home (estimated) is within the GPS bias of the spawn


async def _try(fn):
    try:
        return await fn()
    except Exception:
        return None


async def _mode_is(tel, *modes):
    return await tel.flight_mode() in modes


async def _landed_state_is(tel, state):
    return await tel.landed_state() == state
