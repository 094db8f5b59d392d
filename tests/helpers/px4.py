"""A real-PX4 flight for tests: PX4 SITL instances with SIH (``simulator.px4_sitl``), SIH's truth, a Zenoh rendezvous,
the fleet client, and agent processes (``python -m apps.cli agent``) connected to the instances.

The PX4 build is ``../shared/px4-sitl`` (or ``$SKYCAP_PX4_SITL``); :func:`px4_or_skip` skips a test with the
reason where it is absent. Instances start at ``$SKYCAP_PX4_FIRST_INSTANCE`` (default 0).
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np

ORIGIN = (47.397742, 8.545594, 488.0)


def px4_or_skip() -> Path:
    import pytest

    from simulator.px4_sitl import Px4SitlError, find_px4_folder

    try:
        return find_px4_folder()
    except Px4SitlError as e:
        pytest.skip(f"real PX4 SITL not available: {e}")


class Px4Flight:
    """``n`` PX4 SITL vehicles with homes at ``homes_ne_m`` (world north/east m about :data:`ORIGIN`), their truth,
    a rendezvous + fleet client, and helpers to start agents."""

    def __init__(self, tmp: Path, homes_ne_m: list[tuple[float, float]], params: dict[str, float] | None = None):
        from comms.transport import Transport, TransportConfig
        from groundstation.fleet import FleetClient
        from simulator.px4_sitl import Px4Sitl, SihTruthReader
        from skycap.frames import ned_to_geodetic
        from tests.helpers.ports import free_tcp_port

        self.tmp = tmp
        self.n = len(homes_ne_m)
        self.fleet_id = "p" + uuid.uuid4().hex[:6]
        homes = [ned_to_geodetic([n, e, 0.0], *ORIGIN)[:2] for n, e in homes_ne_m]
        first = int(os.environ.get("SKYCAP_PX4_FIRST_INSTANCE", "0"))
        self.px4 = Px4Sitl(tmp / "px4", self.n, first_instance=first, homes_geodetic=homes,
                           params=params).start()
        self.truth = SihTruthReader([self.px4.truth_port(k) for k in range(self.n)], ORIGIN)
        self.truth_log: list[list[tuple[float, np.ndarray]]] = [[] for _ in range(self.n)]
        self.truth.on_truth = lambda k, t: self.truth_log[k].append((t.t_received_ns * 1e-9, t.position_ned_m))
        assert self.truth.wait_all(10.0), "no SIH truth from PX4"
        #: SIH's ground (AMSL) under each vehicle, from its truth at rest: heights are measured from it
        self.ground_amsl_m = [t.altitude_amsl_m for t in self.truth.latest()]
        self.endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.bus = Transport.open(TransportConfig.rendezvous(self.endpoint), "test")
        self.fleet = FleetClient(self.fleet_id, self.bus, heartbeat_hz=4.0)
        self.procs: dict[str, subprocess.Popen] = {}

    def start_agent(self, k: int, *extra: str) -> subprocess.Popen:
        drone = f"drone_{k + 1}"
        log = open(self.tmp / f"{drone}.log", "a")
        cmd = [sys.executable, "-m", "apps.cli", "agent", "--drone-id", drone, "--fleet", self.fleet_id,
               "--connection", self.px4.connection_url(k), "--record-dir", str(self.tmp / "rec"),
               "--zenoh-connect", self.endpoint, "--set", "record_camera=false", *extra]
        p = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        self.procs[drone] = p
        return p

    def height_m(self, k: int) -> float:
        """SIH's true height of vehicle ``k`` above its ground."""
        return float(self.truth.latest()[k].altitude_amsl_m - self.ground_amsl_m[k])

    def truth_ned(self, k: int) -> np.ndarray:
        """SIH's true position, world NED with down about the vehicle's ground."""
        t = self.truth.latest()[k]
        p = np.array(t.position_ned_m, dtype=float)
        p[2] = -(t.altitude_amsl_m - self.ground_amsl_m[k])
        return p

    def log(self, drone: str) -> str:
        return (self.tmp / f"{drone}.log").read_text()

    def agent_state(self, drone: str) -> str:
        h = self.fleet.healths.get(drone)
        return h.state if h else ""

    def wait_state(self, drone: str, state: str, timeout_s: float) -> bool:
        return self.fleet.wait_until(lambda f: self.agent_state(drone) == state, timeout_s, f"{drone} {state}")

    def wait_all(self, state: str, timeout_s: float) -> bool:
        ids = [f"drone_{k + 1}" for k in range(self.n)]
        return self.fleet.wait_until(lambda f: all(self.agent_state(d) == state for d in ids), timeout_s, state)

    def orbit_errors(self, plan, t0_s: float, t1_s: float) -> dict:
        """Orbit figures against SIH's truth between UNIX times t0_s..t1_s: radius RMS and mean (m), height RMS (m),
        phase RMS (deg) of each vehicle against its slot, and the smallest distance between two vehicles (m)."""
        from onboard.orbit import slot_angle_rad

        c = np.asarray(plan.center_ned_m, dtype=float)
        out = {"radius_rms_m": [], "radius_bias_m": [], "height_rms_m": [], "height_bias_m": [], "phase_rms_deg": []}
        tracks = []
        for k in range(self.n):
            d = f"drone_{k + 1}"
            rows = [(t, p) for t, p in self.truth_log[k] if t0_s <= t <= t1_s]
            t = np.array([r[0] for r in rows])
            p = np.array([r[1] for r in rows], dtype=float)
            p[:, 2] = p[:, 2] + (self.ground_amsl_m[k] - ORIGIN[2])  # truth down about the origin -> about the ground
            tracks.append((t, p))
            r = np.hypot(p[:, 0] - c[0], p[:, 1] - c[1])
            out["radius_rms_m"].append(float(np.sqrt(np.mean((r - plan.radius_m) ** 2))))
            out["radius_bias_m"].append(float(np.mean(r - plan.radius_m)))
            out["height_rms_m"].append(float(np.sqrt(np.mean((-p[:, 2] - plan.altitude_m) ** 2))))
            out["height_bias_m"].append(float(np.mean(-p[:, 2] - plan.altitude_m)))
            ang = np.arctan2(p[:, 1] - c[1], p[:, 0] - c[0])
            slot = np.array([slot_angle_rad(plan, d, ti) for ti in t])
            err = (ang - slot + math.pi) % (2 * math.pi) - math.pi
            out["phase_rms_deg"].append(float(np.degrees(np.sqrt(np.mean(err ** 2)))))
        if self.n > 1:
            tt = np.linspace(t0_s, t1_s, 200)
            pos = [np.stack([np.interp(tt, t, p[:, j]) for j in range(3)], axis=1) for t, p in tracks]
            out["min_separation_m"] = float(min(np.linalg.norm(pos[a] - pos[b], axis=1).min()
                                                for a in range(self.n) for b in range(a + 1, self.n)))
        return out

    def close(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)
        self.fleet.close()
        self.bus.close()
        self.truth.close()
        self.px4.stop()
