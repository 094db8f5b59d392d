"""MAVSDK 4's gimbal plugin (the real library, over UDP loopback) against the simulated vehicle's gimbal:
discovery (the autopilot as gimbal manager), taking control, set_angles -> the reported attitude reaches the
command within the gimbal's rate and lag bounds and respects its limits; and no gimbal when it is disabled.

The measured settle time and steady error are printed (``-s``) and asserted against the dynamics' bounds."""

from __future__ import annotations

import asyncio
import math
import time

import pytest
from mavsdk.asyncio import Configuration, Mavsdk
from mavsdk.asyncio.plugins.gimbal import ControlMode, GimbalAsync, GimbalMode, SendMode
from mavsdk.component_type import ComponentType
from sim_vehicle_helpers import sim_test_config

pytestmark = pytest.mark.timeout(90)


async def _connect(port: int):
    mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER))
    await mavsdk.add_any_connection(f"udpin://0.0.0.0:{port}")
    system = await mavsdk.first_autopilot(10.0)
    assert system is not None
    return mavsdk, system


async def _gimbals(g: GimbalAsync, timeout_s: float):
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        lst = (await g.gimbal_list()).gimbals
        if lst:
            return lst
        await asyncio.sleep(0.1)
    return []


async def _step_response(g: GimbalAsync, gid: int, pitch_deg: float, yaw_deg: float, mode, seconds: float):
    """Command once; [(t since the command was acknowledged, pitch_deg, yaw_deg forward, yaw_deg north)]."""
    trace = []
    att = g.subscribe_attitude()
    await g.set_angles(gid, 0.0, pitch_deg, yaw_deg, mode, SendMode.ONCE)
    t0 = time.monotonic()
    async for a in att:
        t = time.monotonic() - t0
        trace.append((t, a.euler_angle_forward.pitch_deg, a.euler_angle_forward.yaw_deg, a.euler_angle_north.yaw_deg))
        if t > seconds:
            break
    await att.aclose()
    return trace


def _settle_s(trace, axis: int, target_deg: float, tol_deg: float = 1.0) -> float:
    for i, row in enumerate(trace):
        if all(abs(r[axis] - target_deg) <= tol_deg for r in trace[i:]):
            return row[0]
    return math.inf


def test_mavsdk_discovers_controls_and_moves_the_sim_gimbal(sim_world_factory):
    cfg = sim_test_config()
    world = sim_world_factory(cfg)
    v = world.vehicles[0]

    async def run():
        mavsdk, system = await _connect(cfg.ports.offboard_base)
        g = GimbalAsync(system)
        try:
            gimbals = await _gimbals(g, 5.0)
            assert len(gimbals) == 1, "MAVSDK did not discover the simulated gimbal"
            item = gimbals[0]
            assert (item.gimbal_manager_component_id, item.gimbal_device_id, item.model_name) == \
                (1, 1, "sim-gimbal-2axis")
            # MAVSDK's System.has_gimbal() only looks for a MAVLink gimbal *component* (id 154): an autopilot-
            # managed gimbal (PX4 with a non-MAVLink gimbal, this simulator) is found through the gimbal list only
            assert not await system.has_gimbal()
            gid = item.gimbal_id
            await g.take_control(gid, ControlMode.PRIMARY)
            for _ in range(20):  # GIMBAL_MANAGER_STATUS follows the ACK
                status = await g.get_control_status(gid)
                if status.control_mode == ControlMode.PRIMARY:
                    break
                await asyncio.sleep(0.05)
            assert status.control_mode == ControlMode.PRIMARY and v.gimbal.primary_control[1] != 0

            # a 45 deg pitch + 20 deg yaw step (follow mode): rate limited (90 deg/s) + 0.1 s lag
            tr = await _step_response(g, gid, -45.0, 20.0, GimbalMode.YAW_FOLLOW, 2.0)
            settle_p, settle_y = _settle_s(tr, 1, -45.0), _settle_s(tr, 2, 20.0)
            tail = [r for r in tr if r[0] > tr[-1][0] - 0.5]
            err_p = max(abs(r[1] + 45.0) for r in tail)
            err_y = max(abs(r[2] - 20.0) for r in tail)
            rate_hz = (len(tr) - 1) / (tr[-1][0] - tr[0][0])
            print(f"\ngimbal step -45 deg pitch / 20 deg yaw: settled (1 deg) in {settle_p:.2f} s / {settle_y:.2f} s, "
                  f"steady error {err_p:.3f} / {err_y:.3f} deg, reports at {rate_hz:.1f} Hz")
            # bound: 45 deg / 90 deg/s = 0.5 s + lag tail ~0.2 s + one report period + loop latency
            assert settle_p < 1.2 and settle_y < 1.2, (settle_p, settle_y)
            assert err_p < 0.1 and err_y < 0.1
            assert 7.0 < rate_hz < 13.0
            rates = [abs(b[1] - a[1]) / (b[0] - a[0]) for a, b in zip(tr, tr[1:]) if b[0] - a[0] > 0.05]
            assert max(rates) < 90.0 * 1.5  # the rate limit, seen through report jitter

            # beyond the limits: clamped at -90 deg pitch, never past it
            tr = await _step_response(g, gid, -120.0, 0.0, GimbalMode.YAW_FOLLOW, 1.5)
            assert min(r[1] for r in tr) > -90.05 and tr[-1][1] == pytest.approx(-90.0, abs=0.1)
            assert v.gimbal.pitch_rad == pytest.approx(math.radians(-90.0), abs=1e-3)

            # yaw lock: the yaw is relative to north (MAVSDK's euler_angle_north)
            tr = await _step_response(g, gid, -30.0, 35.0, GimbalMode.YAW_LOCK, 1.5)
            assert v.gimbal.yaw_lock
            assert tr[-1][3] == pytest.approx(35.0, abs=3.0)  # the estimated heading's error (~1 deg) included
        finally:
            g.destroy()
            mavsdk.destroy()

    asyncio.run(run())


def test_mavsdk_finds_no_gimbal_when_it_is_disabled(sim_world_factory):
    cfg = sim_test_config(gimbal__enabled=False)
    world = sim_world_factory(cfg)

    async def run():
        mavsdk, system = await _connect(cfg.ports.offboard_base)
        g = GimbalAsync(system)
        try:
            assert await _gimbals(g, 3.0) == []
        finally:
            g.destroy()
            mavsdk.destroy()

    asyncio.run(run())
    assert world.endpoints[0].sent_counts["GIMBAL_DEVICE_ATTITUDE_STATUS"] == 0
