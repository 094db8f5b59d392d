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


class Flight:
    """A simulator with ``n`` vehicles, a rendezvous + fleet client, and helpers to start agents."""

    def __init__(self, tmp: Path, n: int = 1, sim_overrides: list[str] | None = None):
        from groundstation.fleet import FleetClient
        from comms.transport import Transport, TransportConfig
        from tests.helpers.ports import free_tcp_port
        from simulator.config import SimConfig
        from simulator.runner import SimWorld
        from skycap.config import load_config

        self.tmp = tmp
        self.fleet_id = "t" + uuid.uuid4().hex[:6]
        self.base = free_udp_base(n)
        cfg = load_config(SimConfig, overrides=[
            f"vehicles.count={n}", f"ports.offboard_base={self.base}", "ports.local_base=0", "ports.gcs_port=0",
            "vehicles.spacing_m=6", *(sim_overrides or []),
        ])
        self.world = SimWorld(cfg).start_in_thread()
        self.endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.bus = Transport.open(TransportConfig.rendezvous(self.endpoint), "test")
        self.fleet = FleetClient(self.fleet_id, self.bus, heartbeat_hz=4.0)
        self.procs: dict[str, subprocess.Popen] = {}

    def start_agent(self, i: int, *extra: str) -> subprocess.Popen:
        drone = f"drone_{i + 1}"
        log = open(self.tmp / f"{drone}.log", "w")
        cmd = [sys.executable, "-m", "apps.cli", "agent", "--drone-id", drone, "--fleet", self.fleet_id,
               "--connection", f"udpin://0.0.0.0:{self.base + i}", "--record-dir", str(self.tmp),
               "--zenoh-connect", self.endpoint, *extra]
        p = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        self.procs[drone] = p
        return p

    def truth(self, i: int = 0) -> np.ndarray:
        return np.array(self.world.truths()[i].position_ned_m)

    def log(self, drone: str) -> str:
        return (self.tmp / f"{drone}.log").read_text()

    def agent_state(self, drone: str) -> str:
        h = self.fleet.healths.get(drone)
        return h.state if h else ""

    def wait_state(self, drone: str, state: str, timeout_s: float) -> bool:
        return self.fleet.wait_until(lambda f: self.agent_state(drone) == state, timeout_s, f"{drone} {state}")

    def close(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)
        self.fleet.close()
        self.bus.close()
        self.world.stop()
