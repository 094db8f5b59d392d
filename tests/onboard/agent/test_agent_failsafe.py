"""The agent's track-mode failsafe wiring, in process (fake autopilot and bus, real tracking stage, formation
MPC and supervisor): person lost -> hold and search, found -> resume; teammate lost -> re-space (new slot
angle); low battery -> return through the mission and the autopilot; every change logged and in the stats."""

from __future__ import annotations

import asyncio
import dataclasses
import math
import time
from types import SimpleNamespace

import numpy as np

from groundstation.fleet import make_orbit_plan
from onboard.agent import Agent
from onboard.agent.telemetry import Telemetry
from onboard.config import AgentConfig
from onboard.mission import State
from shared_msgs import VehicleState, encode, keys


class FakeAutopilot:
    def __init__(self):
        self.telemetry = Telemetry(battery_remaining_frac=0.9, armed=True, in_air=True, flight_mode="OFFBOARD",
                                   landed_state="in_air", velocity_ned_m_s=(0.0, 0.0, 0.0),
                                   position_ned_m=(8.0, 0.0, -6.0), health_ok=True)
        self.on_state = None
        self.calls: list[str] = []

    async def return_to_launch(self):
        self.calls.append("return")

    async def land(self):
        self.calls.append("land")

    async def hold(self):
        self.calls.append("hold")


class FakeBus:
    def publish(self, key, msg, latch=False):
        return encode(msg)


def _state(d: str, pos) -> SimpleNamespace:
    msg = VehicleState(header=VehicleState.make_header(d), position_ned_m=tuple(pos), velocity_ned_m_s=(0.0, 0.0, 0.0),
                       q_world_body=(1.0, 0.0, 0.0, 0.0))
    return SimpleNamespace(key=keys.drone_key("f", d, keys.STATE), msg=msg)


def test_agent_acts_on_formation_failsafes():
    async def main():
        ap = FakeAutopilot()
        agent = Agent(AgentConfig(drone_id="drone_1", fleet="f", mode="track"), FakeBus(), ap)
        ids = ["drone_1", "drone_2", "drone_3"]
        phases = {"drone_1": 0.0, "drone_2": 2 * math.pi / 3, "drone_3": -2 * math.pi / 3}
        plan = make_orbit_plan(ids, (0.0, 0.0, 0.0), 8.0, 6.0, 0.0, 1, phase_offset_rad=phases)
        agent.mission.set_plan(plan)
        agent.mission.state = State.ORBIT
        src = agent.formation.build_source(plan)
        agent.source = src
        pos = {d: (8.0 * math.cos(a), 8.0 * math.sin(a), -6.0) for d, a in phases.items()}
        own = np.asarray(pos["drone_1"])
        t = time.time()

        def step(dt):
            for d in ("drone_2", "drone_3"):
                if d in alive:
                    agent.on_neighbour_state(_state(d, pos[d]))
            agent.formation.supervise(src, t + dt, own)
            src.update(t + dt, own, np.zeros(3), 0.0)

        alive = {"drone_2", "drone_3"}
        step(0.0)  # the start: nothing seen yet, within the acquisition grace time
        assert not src.holding and abs(src.slot_angle_rad) < 1e-9 and agent.failsafes.log.events == []
        agent.failsafes.t_person_seen_s = time.time() - 5.0  # the person was last seen 5 s ago
        step(0.0)
        assert src.holding and src.search_yaw_rate_rad_s > 0
        np.testing.assert_allclose(src.hold_position_ned_m, own)
        assert agent.failsafes.log.events[-1]["action"] == "hold_and_search"
        agent.failsafes.t_person_seen_s = time.time()  # found again
        step(0.0)
        assert not src.holding and agent.failsafes.log.events[-1]["action"] == "continue"
        # drone_3 falls silent: after teammate_lost_after_s the others re-space
        alive = {"drone_2"}
        agent.teammates.seen_unix_s["drone_3"] = time.time() - 3.0
        agent.failsafes.t_person_seen_s = time.time()
        step(0.0)
        ev = agent.failsafes.log.events[-1]
        assert ev["action"] == "respace" and ev["present"] == ["drone_1", "drone_2"]
        assert abs(src.slot_angle_rad) > math.radians(10) and ev["slot_angle_rad"] == round(src.slot_angle_rad, 4)
        # low battery: return through the mission and the autopilot
        ap.telemetry = dataclasses.replace(ap.telemetry, battery_remaining_frac=0.2)
        step(0.0)
        await asyncio.sleep(0.05)
        assert agent.mission.state == State.RETURNING and ap.calls == ["return"] and agent.source is None
        st = agent.tracking_stats()
        assert st["failsafe_counts"]["hold_and_search"] == 1 and st["failsafe_counts"]["respace"] == 1
        assert st["failsafe_counts"]["return"] == 1 and st["failsafe_counts"]["mission:return"] == 1
        assert any("formation failsafe: respace" in w for w in agent.warnings)

    asyncio.run(main())


def _vs(t_s: float, pos, vel) -> VehicleState:
    return VehicleState(header=VehicleState.make_header("drone_1", int(t_s * 1e9)), position_ned_m=tuple(pos),
                        velocity_ned_m_s=tuple(vel), q_world_body=(1.0, 0.0, 0.0, 0.0))


def test_agent_detects_a_gps_jump_and_takes_it_back():
    agent = Agent(AgentConfig(drone_id="drone_1", fleet="f", mode="track"), FakeBus(), FakeAutopilot())
    t0 = 1000.0
    v = (2.0, 0.0, 0.0)
    for i in range(50):  # flying north at 2 m/s, 50 Hz; then a delayed sample and a burst: not a jump
        agent._on_state(_vs(t0 + 0.02 * i, (2.0 * 0.02 * i, 0.0, -6.0), v))
    agent._on_state(_vs(t0 + 1.4, (2.0 * 1.0, 0.0, -6.0), v))  # arrived 0.4 s late, moved 2 cm
    agent._on_state(_vs(t0 + 1.4005, (2.0 * 1.02, 0.0, -6.0), v))
    assert agent.failsafes.log.events == [] and not agent.tracking.stage.position_correction(int(2000e9)).any()
    agent._on_state(_vs(t0 + 1.42, (2.0 * 1.04 + 3.0, 0.0, -6.0), v))  # +3 m north in 20 ms
    ev = agent.failsafes.log.events[-1]
    assert ev["action"] == "gps_jump" and ev["source"] == "estimator"
    assert agent.failsafes.log.counts == {"estimator:gps_jump": 1}
    t_j = int((t0 + 1.42) * 1e9)
    np.testing.assert_allclose(agent.tracking.stage.position_correction(t_j), [3.0, 0.0, 0.0], atol=0.02)
    assert not agent.tracking.stage.position_correction(t_j - 1).any()
    # the planning position is taken back by it (no track yet: the correction alone)
    np.testing.assert_allclose(agent.formation.feed(agent.formation.build_source(make_orbit_plan(
        ["drone_1"], (0.0, 0.0, 0.0), 8.0, 6.0, 0.0, 1)), t0 + 1.42 + 30.0), [3.0 * math.exp(-1.0), 0.0, 0.0], atol=0.02)
