"""systemd's notify protocol, without systemd: the adapter (:mod:`skycap.sdnotify`) alone and against a real
datagram socket, the agent's control loop as the watchdog's only source of pings (a stuck loop stops them), and
the agent's policy when it starts with the vehicle already in the air (``safety.on_restart_airborne``)."""

from __future__ import annotations

import asyncio
import os
import socket
import tempfile
import threading
import time
from pathlib import Path

import pytest

from onboard.agent import Agent
from onboard.agent.telemetry import Telemetry
from onboard.config import AgentConfig
from onboard.mission import State
from onboard.setpoint import HoldSource
from shared_msgs import VehicleState, encode
from skycap.config import ConfigError
from skycap.sdnotify import Notifier, watchdog_timeout_s


class FakeClock:
    def __init__(self):
        self.t_s = 100.0

    def __call__(self) -> float:
        return self.t_s


def test_every_call_is_a_no_op_without_notify_socket(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    monkeypatch.setenv("WATCHDOG_USEC", "1000000")
    sent: list[str] = []
    for n in (Notifier(send=sent.append), Notifier.from_env(), Notifier.disabled()):
        n.status("x")
        n.ready("y")
        assert not n.watchdog()
        n.stopping()
        assert not n.enabled and n.watchdog_timeout_s is None and not n.ready_sent
    assert sent == []


def test_watchdog_follows_watchdog_usec_and_pid():
    assert watchdog_timeout_s({}) is None
    assert watchdog_timeout_s({"WATCHDOG_USEC": "2000000"}) == 2.0
    assert watchdog_timeout_s({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid())}) == 2.0
    assert watchdog_timeout_s({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"}, pid=4242) is None  # another's
    assert watchdog_timeout_s({"WATCHDOG_USEC": "0"}) is None
    assert watchdog_timeout_s({"WATCHDOG_USEC": "soon"}) is None

    clock, sent = FakeClock(), []
    n = Notifier({"NOTIFY_SOCKET": "/run/x", "WATCHDOG_USEC": "2000000"}, send=sent.append, clock=clock)
    assert n.ping_period_s == 0.5  # a quarter of the timeout: systemd asks for at least every half
    assert n.watchdog() and sent == ["WATCHDOG=1"]
    for _ in range(11):  # called every 50 ms (the control loop) for 0.55 s: one more ping
        clock.t_s += 0.05
        n.watchdog()
    assert sent == ["WATCHDOG=1"] * 2 and n.pings == 2
    # no NOTIFY_SOCKET or no watchdog: never a ping
    assert not Notifier({"WATCHDOG_USEC": "2000000"}, send=sent.append).watchdog()
    assert not Notifier({"NOTIFY_SOCKET": "/run/x"}, send=sent.append).watchdog()
    assert len(sent) == 2


def test_status_ready_and_stopping_messages():
    sent: list[str] = []
    n = Notifier({"NOTIFY_SOCKET": "/run/x"}, send=sent.append)
    n.status("connecting to the autopilot\n on udp")
    n.status("connecting to the autopilot on udp")  # unchanged: not sent again
    n.ready("ready, idle")
    n.ready("ready, idle")  # READY once
    n.status("hover")
    n.stopping("stopping")
    assert sent == ["STATUS=connecting to the autopilot on udp", "READY=1\nSTATUS=ready, idle", "STATUS=hover",
                    "STOPPING=1\nSTATUS=stopping"]

    def broken(_msg):
        raise OSError("no such socket")

    b = Notifier({"NOTIFY_SOCKET": "/run/x", "WATCHDOG_USEC": "1000000"}, send=broken)
    b.ready()  # logged, never raised: the service keeps running
    assert not b.ready_sent and not b.watchdog()


def _bound_socket() -> tuple[socket.socket, str]:
    path = os.path.join(tempfile.mkdtemp(prefix="sdn"), "notify.sock")  # short: AF_UNIX paths are <= 107 bytes
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(path)
    s.settimeout(2.0)
    return s, path


def test_the_library_delivers_the_datagrams(monkeypatch):
    pytest.importorskip("cysystemd", reason="cysystemd is the sd_notify library on Linux (pyproject base deps)")
    s, path = _bound_socket()
    try:
        monkeypatch.setenv("NOTIFY_SOCKET", path)
        monkeypatch.setenv("WATCHDOG_USEC", "4000000")
        n = Notifier.from_env()
        assert n.enabled and n.watchdog_timeout_s == 4.0
        n.status("waiting")
        n.ready("up")
        assert n.watchdog()
        n.stopping()
        got = [s.recv(4096).decode() for _ in range(4)]
        assert got == ["STATUS=waiting", "READY=1\nSTATUS=up", "WATCHDOG=1", "STOPPING=1"]
    finally:
        s.close()
        os.unlink(path)
        os.rmdir(os.path.dirname(path))


# --- the agent --------------------------------------------------------------------------------------------
class FakeBus:
    def publish(self, key, msg, latch=False):
        return encode(msg)


class FakeAutopilot:
    """On the ground unless ``airborne``; ``stuck`` makes the next setpoint an await that never returns (a MAVSDK
    call hung on a dead link)."""

    def __init__(self, airborne: bool = False):
        self.telemetry = Telemetry(armed=airborne, in_air=airborne, landed_state="in_air" if airborne else "on_ground",
                                   flight_mode="HOLD" if airborne else "READY", position_ned_m=(0.0, 0.0, -5.0),
                                   health_ok=True)
        self.on_state = self.on_gimbal = None
        self.mode_changes: list = []
        self.offboard_active = False
        self.stuck = False
        self.setpoints = 0
        self.calls: list[str] = []

    async def set_setpoint(self, sp) -> None:
        self.setpoints += 1
        if self.stuck:
            await asyncio.Event().wait()

    async def set_gimbal_pitch(self, pitch_rad: float) -> bool:
        return False

    async def land(self) -> None:
        self.calls.append("land")

    async def return_to_launch(self) -> None:
        self.calls.append("return")

    async def hold(self) -> None:
        self.calls.append("hold")


def _state() -> VehicleState:
    return VehicleState(header=VehicleState.make_header("drone_1"), position_ned_m=(0.0, 0.0, -5.0),
                        velocity_ned_m_s=(0.0, 0.0, 0.0), q_world_body=(1.0, 0.0, 0.0, 0.0), landed_state="in_air")


def test_a_stuck_control_loop_stops_the_watchdog_pings():
    timeout_s = 0.6  # WATCHDOG_USEC: pings due every 0.15 s (at the next 20 Hz tick), required every 0.3 s
    sent: list[tuple[float, str]] = []

    async def main():
        ap = FakeAutopilot()
        n = Notifier({"NOTIFY_SOCKET": "/run/x", "WATCHDOG_USEC": str(int(timeout_s * 1e6))},
                     send=lambda m: sent.append((time.monotonic(), m)))
        agent = Agent(AgentConfig(drone_id="drone_1", fleet="f"), FakeBus(), ap, notifier=n)
        task = asyncio.create_task(agent.control_loop())
        await asyncio.sleep(0.3)
        assert not n.ready_sent  # no telemetry yet: not ready, says so
        agent.state = _state()
        agent.source = HoldSource((0.0, 0.0, -5.0), 0.0)
        await asyncio.sleep(1.2)
        t_stall = time.monotonic()
        ap.stuck = True  # the next setpoint never returns: the control loop is stuck in it
        await asyncio.sleep(1.0)
        assert not task.done()
        task.cancel()
        return ap, t_stall

    ap, t_stall = asyncio.run(main())
    assert ap.setpoints > 10
    texts = [m for _, m in sent]
    i_ready = next(i for i, m in enumerate(texts) if m.startswith("READY=1"))
    assert any(m.startswith("STATUS=") and "waiting for the first telemetry" in m for m in texts[:i_ready])
    pings = [t for t, m in sent if m == "WATCHDOG=1"]
    before = [t for t in pings if t <= t_stall]
    gaps = [b - a for a, b in zip(before, before[1:])]
    assert len(before) >= 6 and max(gaps) < timeout_s / 2, gaps  # while it ran: at least every half timeout
    # stuck: at most the ping at the top of the tick that then hung, and none for the rest of the second
    # (systemd would have restarted the agent 0.6 s after the last one)
    after = [t - t_stall for t in pings if t > t_stall]
    assert len(after) <= 1 and all(dt < 0.1 for dt in after), after


def _link_up(policy: str) -> tuple[Agent, FakeAutopilot, list[str]]:
    sent: list[str] = []

    async def main():
        ap = FakeAutopilot(airborne=True)
        cfg = AgentConfig(drone_id="drone_1", fleet="f")
        cfg.safety.on_restart_airborne = policy
        agent = Agent(cfg, FakeBus(), ap, notifier=Notifier({"NOTIFY_SOCKET": "/run/x"}, send=sent.append))
        agent.state = _state()
        agent._systemd_tick()
        await asyncio.sleep(0.05)  # the spawned landing runs
        return agent, ap

    agent, ap = asyncio.run(main())
    return agent, ap, sent


def test_an_agent_started_in_flight_lands_or_resumes_by_policy():
    agent, ap, sent = _link_up("land")
    assert agent.mission.state == State.LANDING and ap.calls == ["land"]
    assert any("started with the vehicle airborne" in w for w in agent.warnings)
    assert sent[-1].startswith("READY=1")

    agent, ap, sent = _link_up("resume")
    assert agent.mission.state == State.HOVER and ap.calls == [] and agent.mission.airborne
    assert sent[-1].startswith("READY=1") and "hover" in sent[-1]

    cfg = AgentConfig()
    cfg.safety.on_restart_airborne = "continue"
    with pytest.raises(ConfigError, match="on_restart_airborne.*'land' or 'resume'"):
        cfg.validate()


def test_example_config_documents_the_restart_policy():
    text = (Path(__file__).resolve().parents[2] / "deploy" / "agent.example.toml").read_text()
    assert 'on_restart_airborne = "land"' in text


def test_camera_service_under_the_notify_protocol(tmp_path, monkeypatch, bus_pair):
    """``skycap camera serve`` (skycap-camera.service): READY once publishing, watchdog pings from its capture
    loop, STOPPING when stopped."""
    pytest.importorskip("cysystemd", reason="cysystemd is the sd_notify library on Linux (pyproject base deps)")
    import cv2
    import numpy as np

    from onboard.camera.service import serve
    from skycap.config import load_config
    from tests.onboard.camera.support import write_calibration

    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(4):
        cv2.imwrite(str(frames / f"im{i}.jpg"), np.full((48, 64, 3), 40 * i, np.uint8))
    cal = write_calibration(tmp_path / "camera.toml", 64, 48)
    a, _ = bus_pair
    toml = tmp_path / "agent.toml"
    toml.write_text(f'drone_id = "drone_3"\nfleet = "f9"\n[camera]\nsource = "file"\nuri = "{frames}"\n'
                    f'rate_hz = 20.0\ncalibration_file = "{cal}"\n')
    cfg = load_config(AgentConfig, toml, [f'transport.connect=["{a.config.listen[0]}"]'])
    s, path = _bound_socket()
    s.settimeout(0.2)
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    monkeypatch.setenv("WATCHDOG_USEC", "400000")
    got: list[tuple[float, str]] = []
    stop = threading.Event()
    rc: list[int] = []
    t = threading.Thread(target=lambda: rc.append(serve(cfg, stop=stop)))
    try:
        t.start()
        t_end = time.monotonic() + 3.0
        while time.monotonic() < t_end:
            try:
                got.append((time.monotonic(), s.recv(4096).decode()))
            except socket.timeout:
                pass
        stop.set()
        t.join(10)
        while True:
            try:
                got.append((time.monotonic(), s.recv(4096).decode()))
            except socket.timeout:
                break
    finally:
        stop.set()
        s.close()
        os.unlink(path)
        os.rmdir(os.path.dirname(path))
    texts = [m for _, m in got]
    assert rc == [0] and texts[0].startswith("STATUS=camera cam0 of drone_3: starting"), texts[:3]
    i_ready = next(i for i, m in enumerate(texts) if m.startswith("READY=1"))
    assert any("delivering" in m for m in texts[i_ready:]), texts
    pings = [t for t, m in got if m == "WATCHDOG=1"]
    # systemd restarts the service when no ping arrives within WATCHDOG_USEC (0.4 s): every gap stays inside it
    # (the service aims at half of it; how close it gets on a loaded machine is not the contract)
    assert len(pings) >= 5 and max(b - a for a, b in zip(pings, pings[1:])) < 0.4, pings
    assert texts[-1].startswith("STOPPING=1")
