"""The agent's gimbal: the pure parts (report -> GimbalAttitude, boot-time clock, the "does it follow" watch and
its health warning), the MAVSDK adapter against the simulator's gimbal (discovery without ``has_gimbal``,
set_angles, attitude reports: settle time and error), and the agent process publishing and recording
``<drone>/gimbal``."""

from __future__ import annotations

import asyncio
import math
import signal
import time
from types import SimpleNamespace

import numpy as np
import pytest

from onboard.agent.autopilot import MavsdkAutopilot
from onboard.agent.gimbal import BootClock, GimbalWatch, attitude_message
from onboard.agent.loop import Agent
from onboard.config import AgentConfig
from shared_msgs import GimbalAttitude, keys

D = math.radians


def _att(pitch_deg, yaw_deg, north_yaw_deg=math.nan, t_us=1_000_000, gid=1):
    e = lambda r, p, y: SimpleNamespace(roll_deg=r, pitch_deg=p, yaw_deg=y)  # noqa: E731
    return SimpleNamespace(gimbal_id=gid, euler_angle_forward=e(0.0, pitch_deg, yaw_deg),
                           euler_angle_north=e(0.0, pitch_deg, north_yaw_deg),
                           angular_velocity=SimpleNamespace(roll_rad_s=0.0, pitch_rad_s=0.1, yaw_rad_s=math.nan),
                           timestamp_us=t_us)


# --- pure ------------------------------------------------------------------------------------------------
def test_attitude_message_and_boot_clock():
    m = attitude_message("drone_1", _att(-30.0, 10.0), 5, 7, vehicle_yaw_rad=D(175.0))
    assert isinstance(m, GimbalAttitude) and m.header.t_measurement_ns == 5 and m.header.seq == 7
    assert (m.pitch_rad, m.yaw_rad) == pytest.approx((D(-30.0), D(10.0)))
    assert m.yaw_north_rad == pytest.approx(D(-175.0))  # 10 + 175, wrapped
    assert m.angular_velocity_rad_s == (0.0, 0.1, 0.0)
    assert attitude_message("d", _att(0, 0, 42.0), 0, 0).yaw_north_rad == pytest.approx(D(42.0))
    c = BootClock()
    assert c.to_wall_ns(1_000_000, 10_000_000_000 + 30_000_000) == 10_030_000_000  # 30 ms delay so far
    assert c.to_wall_ns(1_100_000, 10_100_000_000 + 5_000_000) == 10_105_000_000  # 5 ms: the better offset
    assert c.to_wall_ns(1_200_000, 10_300_000_000) == 10_205_000_000  # a late arrival keeps the offset
    assert c.to_wall_ns(50_000, 20_000_000_000) == 20_000_000_000  # stamps went back (reboot): offset reset
    assert c.to_wall_ns(0, 123) == 123


def test_boot_clock_follows_a_sender_clock_that_falls_behind():
    """A simulator's clock that runs at 80 % of the wall clock (a loaded machine): each stamp is mapped within the
    window's drift (1 s x 20 % = 0.2 s at most) plus the transport delay, not seconds off as with one fixed offset."""
    rng = np.random.default_rng(0)
    c = BootClock(window_s=1.0)
    errs = []
    for k in range(400):  # 40 s of reports at 10 Hz
        wall_ns = 10**10 + k * 100_000_000
        stamp_us = (k * 100_000_000 * 8 // 10) // 1000 + 1  # the sender's time, 0.8 x wall
        arrival = wall_ns + int(rng.uniform(1e6, 20e6))
        errs.append(c.to_wall_ns(stamp_us, arrival) - wall_ns)
    errs = np.abs(errs[20:]) * 1e-9
    assert errs.max() < 0.25, errs.max()  # one offset kept from the start would be 7.6 s off at the end


def test_gimbal_watch_warns_once_when_the_command_is_not_reached():
    w = GimbalWatch(tolerance_deg=2.0, settle_timeout_s=3.0)
    assert w.check(100.0) is None  # nothing commanded
    w.command(0.0, D(-40.0))
    w.report(0.5, D(-20.0), 0.0)
    assert w.check(2.9) is None
    w.report(1.0, D(-39.0), D(1.0))  # within 2 deg: reached
    assert w.check(10.0) is None
    w.command(20.0, D(-60.0))
    w.command(20.5, D(-61.0))  # a newer command before reaching: still timed from 20.0
    w.report(22.0, D(-45.0), 0.0)  # stuck (e.g. at a limit)
    msg = w.check(23.1)
    assert msg is not None and "not following" in msg and "-61.0" in msg and "-45.0" in msg
    assert w.check(30.0) is None and w.warnings == 1  # once per command
    w.command(40.0, D(-10.0))
    assert "not reporting" in w.check(44.0)  # no report since the command
    w2 = GimbalWatch()
    w2.command(0.0, D(-10.0))
    assert "not reporting" in w2.check(3.5)


class _Bus:
    def __init__(self):
        self.sent = []

    def publish(self, key, msg, latch=False):
        self.sent.append((key, msg))
        from shared_msgs import encode, stamp_sent

        return encode(stamp_sent(msg))


class _Recorder:
    def __init__(self):
        self.records = []

    def record(self, channel, data, log_time_ns=None):
        self.records.append(channel)


class _Autopilot:
    def __init__(self, reach: bool):
        from onboard.agent.telemetry import Telemetry

        self.telemetry = Telemetry()
        self.on_state = self.on_gimbal = None
        self.reach = reach
        self.sent: list[float] = []

    async def set_gimbal_pitch(self, pitch_rad):
        self.sent.append(pitch_rad)
        await asyncio.sleep(0.05)  # the ACK's round trip: must not hold up the control loop
        if self.reach:
            self.on_gimbal(attitude_message("drone_1", _att(math.degrees(pitch_rad), 0.0), 1, 1))
        return True


def test_agent_publishes_records_and_warns_about_a_gimbal_that_does_not_follow():
    from onboard.setpoint import Setpoint

    async def run(reach: bool):
        bus, rec, ap = _Bus(), _Recorder(), _Autopilot(reach)
        agent = Agent(AgentConfig(drone_id="drone_1", fleet="f"), bus, ap, rec)
        assert ap.on_gimbal == agent._on_gimbal
        sp = Setpoint(position_ned_m=(0.0, 0.0, -5.0), velocity_ned_m_s=(0.0, 0.0, 0.0),
                      acceleration_ned_m_s2=(0.0, 0.0, 0.0), yaw_rad=0.0, gimbal_pitch_rad=D(-35.0))
        t0 = time.monotonic()
        await agent._point_gimbal(sp)
        assert time.monotonic() - t0 < 0.02  # sent in the background
        await agent._point_gimbal(sp)  # in flight / too soon: not sent again
        await asyncio.sleep(0.1)
        assert ap.sent == [D(-35.0)]
        agent.gimbal_watch.settle_timeout_s = 0.2
        await asyncio.sleep(0.25)
        agent._check_gimbal(time.monotonic())
        return bus, rec, agent

    bus, rec, agent = asyncio.run(run(reach=True))
    assert [k for k, _ in bus.sent] == [keys.drone_key("f", "drone_1", keys.GIMBAL)]
    assert rec.records == ["gimbal"] and agent.warnings == []
    _, _, agent = asyncio.run(run(reach=False))
    assert len(agent.warnings) == 1 and "gimbal not reporting" in agent.warnings[0]
    assert not agent.health().ok and agent.health().warnings == agent.warnings


# --- the MAVSDK adapter against the simulator's gimbal (real mavsdk_server, UDP loopback) ------------------
def test_autopilot_discovers_commands_and_reads_the_sim_gimbal():
    from simulator.config import SimConfig
    from simulator.runner import SimWorld
    from tests.helpers.ports import free_udp_base

    cfg = SimConfig()
    cfg.ports.offboard_base, cfg.ports.local_base, cfg.ports.gcs_port = free_udp_base(1), 0, 0
    cfg.gimbal.initial_pitch_deg = -10.0
    world = SimWorld(cfg).start_in_thread()
    reports: list[tuple[float, GimbalAttitude]] = []

    async def run():
        ap = MavsdkAutopilot("drone_1")
        ap.on_gimbal = lambda m: reports.append((time.monotonic(), m))
        try:
            await ap.connect(f"udpin://0.0.0.0:{cfg.ports.offboard_base}", 10.0)
            await ap.start_telemetry(50.0)
            t_end = time.monotonic() + 8.0
            while not (ap.has_gimbal and reports) and time.monotonic() < t_end:
                await asyncio.sleep(0.05)
            assert ap.has_gimbal and reports, "the agent's adapter did not discover the simulated gimbal"
            assert world.vehicles[0].gimbal.primary_control != (0, 0)  # took control
            assert reports[-1][1].pitch_rad == pytest.approx(D(-10.0), abs=1e-3)  # the initial pitch
            assert await ap.set_gimbal_pitch(D(-40.0))
            t_cmd = time.monotonic()
            await asyncio.sleep(2.0)
            return t_cmd, ap.telemetry
        finally:
            await ap.close()

    try:
        t_cmd, tel = asyncio.run(run())
    finally:
        world.stop()
    after = [(t - t_cmd, m) for t, m in reports if t >= t_cmd]
    settle = next(t for i, (t, _) in enumerate(after)
                  if all(abs(m.pitch_rad - D(-40.0)) <= D(1.0) for _, m in after[i:]))
    tail = [m for t, m in after if t > after[-1][0] - 0.5]
    err = max(abs(math.degrees(m.pitch_rad) + 40.0) for m in tail)
    stamps = [m.header.t_measurement_ns for _, m in after]
    print(f"\nagent adapter: -10 -> -40 deg pitch settled (1 deg) {settle:.2f} s after the ACK, steady error {err:.3f} "
          f"deg, {len(after) / after[-1][0]:.1f} reports/s")
    assert settle < 1.2 and err < 0.1
    assert all(b > a for a, b in zip(stamps, stamps[1:]))  # the gimbal's own clock, mapped to wall time
    assert tel.gimbal_id == 1 and tel.gimbal_pitch_rad == pytest.approx(D(-40.0), abs=D(0.1))
    assert abs(tel.gimbal_yaw_rad) < 1e-3


@pytest.mark.slow
def test_agent_process_publishes_and_records_the_gimbal(flight):
    from flightdata.flightlog import FlightLog
    from flightdata.folder import FlightFolder

    fl = flight(1, ["gimbal.initial_pitch_deg=-25"])
    got: list[GimbalAttitude] = []
    sub = fl.bus.subscribe(keys.drone_key(fl.fleet_id, "drone_1", keys.GIMBAL), lambda rx: got.append(rx.msg),
                           GimbalAttitude)
    proc = fl.start_agent(0)
    t_end = time.monotonic() + 30.0
    while len(got) < 20 and time.monotonic() < t_end:
        time.sleep(0.1)
    assert len(got) >= 20, fl.log("drone_1")
    assert got[-1].pitch_rad == pytest.approx(D(-25.0), abs=1e-3) and got[-1].header.sender_id == "drone_1"
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(30) == 0, fl.log("drone_1")
    sub.close()
    [sortie] = FlightFolder(fl.tmp).sorties("drone_1")
    n = FlightLog(sortie.path).topic_counts().get("gimbal", 0)
    assert n >= 20, FlightLog(sortie.path).topic_counts()
    assert "gimbal 1 discovered" in fl.log("drone_1")
