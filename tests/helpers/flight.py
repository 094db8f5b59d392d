"""A simulated flight for tests: the built-in simulator (in a thread), a Zenoh rendezvous, the fleet client, and
agent processes (``python -m apps.cli agent``), all on non-default ports. The ``flight`` fixture (tests/conftest.py)
makes them."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import uuid
from pathlib import Path

import numpy as np

from tests.helpers.ports import free_udp_base


class AgentFleet:
    """A Zenoh rendezvous + fleet client on a free port, and agent processes (``python -m apps.cli agent``) with their
    logs in ``tmp``: what every test flight has, whatever flies the vehicles."""

    def __init__(self, tmp: Path, fleet_prefix: str = "t"):
        from comms.transport import Transport, TransportConfig
        from groundstation.fleet import FleetClient
        from tests.helpers.ports import free_tcp_port

        self.tmp = tmp
        self.fleet_id = fleet_prefix + uuid.uuid4().hex[:6]
        self.endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.bus = Transport.open(TransportConfig.rendezvous(self.endpoint), "test")
        self.fleet = FleetClient(self.fleet_id, self.bus, heartbeat_hz=4.0)
        self.procs: dict[str, subprocess.Popen] = {}

    def _spawn_agent(self, drone: str, connection: str, record_dir: Path, *extra: str) -> subprocess.Popen:
        log = open(self.tmp / f"{drone}.log", "a")
        cmd = [sys.executable, "-m", "apps.cli", "agent", "--drone-id", drone, "--fleet", self.fleet_id,
               "--connection", connection, "--record-dir", str(record_dir), "--zenoh-connect", self.endpoint, *extra]
        p = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        self.procs[drone] = p
        return p

    def log(self, drone: str) -> str:
        return (self.tmp / f"{drone}.log").read_text()

    def agent_state(self, drone: str) -> str:
        h = self.fleet.healths.get(drone)
        return h.state if h else ""

    def wait_state(self, drone: str, state: str, timeout_s: float) -> bool:
        return self.fleet.wait_until(lambda f: self.agent_state(drone) == state, timeout_s, f"{drone} {state}")

    def kill_agents(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)

    def close(self) -> None:
        self.kill_agents()
        self.fleet.close()
        self.bus.close()


class Flight(AgentFleet):
    """A simulator with ``n`` vehicles, a rendezvous + fleet client, and helpers to start agents."""

    def __init__(self, tmp: Path, n: int = 1, sim_overrides: list[str] | None = None):
        from simulator.config import SimConfig
        from simulator.runner import SimWorld
        from skycap.config import load_config

        self.base = free_udp_base(n)
        cfg = load_config(SimConfig, overrides=[
            f"vehicles.count={n}", f"ports.offboard_base={self.base}", "ports.local_base=0", "ports.gcs_port=0",
            "vehicles.spacing_m=6", *(sim_overrides or []),
        ])
        self.world = SimWorld(cfg).start_in_thread()
        super().__init__(tmp)

    def start_agent(self, i: int, *extra: str) -> subprocess.Popen:
        return self._spawn_agent(f"drone_{i + 1}", f"udpin://0.0.0.0:{self.base + i}", self.tmp, *extra)

    def truth(self, i: int = 0) -> np.ndarray:
        return np.array(self.world.truths()[i].position_ned_m)

    def close(self) -> None:
        super().close()
        self.world.stop()
