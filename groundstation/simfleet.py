"""The built-in simulated fleet for ``skycap gs --sim N``: simulator, one camera node and one agent per drone.

NOTE: this repeats the process launching of :func:`apps.demo.run_demo` (same commands and ``--set`` options:
``skycap sim``, ``python -m simulator.scene.node``, ``skycap agent``), because the ground station sits below
``apps`` in the import layers and cannot import it. The process supervision (:class:`skycap.childproc.ProcessSupervisor`)
and the free ports (:mod:`skycap.ports`) are shared; the launch commands should move into a lower layer too.

    fleet = SimFleet.prepare(n=2, out="flights/gs-...")   # temporary CA, free endpoint and ports
    fleet = SimFleet.prepare(n=2, out=..., mode="track")  # agents in track mode: they find and follow the person
    bus = Transport.open(TransportConfig.rendezvous(fleet.endpoint, fleet.keys_dir), "gs", identity="gcs")
    fleet.start()                                           # the processes join the app's rendezvous
    ...
    fleet.stop()
"""

from __future__ import annotations

import logging
import math
import shutil
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from comms.security import FleetKeys
from skycap.childproc import ProcessSupervisor
from skycap.ports import free_tcp_port, free_udp_base
from flightdata.folder import FlightFolder
from onboard.orbit import evenly_spaced_phases
from skycap.errors import SkycapError

log = logging.getLogger(__name__)

__all__ = ["SimFleet"]


@dataclass
class SimFleet:
    """A simulated fleet of ``len(ids)`` drones spawned under the slots of an orbit of ``radius_m`` around the
    origin, recording into ``out`` (a new flight folder), secured by a temporary fleet CA in ``keys_dir``.

    ``mode``: the agents' mode: "orbit" (fly the plan's circle) or "track" (active capture, as ``skycap demo --mode
    track`` runs them: each agent fuses its own and its teammates' detections of the person (the simulator's box
    detector on its camera, ``track.detections = "sim"``) and flies the formation MPC around the fused estimate;
    the cameras are needed). The person starts near the origin."""

    ids: list[str]
    out: Path
    endpoint: str
    keys_dir: str
    fleet: str = "gs-sim"
    radius_m: float = 8.0
    altitude_m: float = 6.0
    cameras: bool = True
    sim_set: list[str] = field(default_factory=list)
    mode: str = "orbit"
    #: track mode: the person's box height given to the agents (m; the simulator's person box measures ~1.95 m,
    #: see apps.demo.TrackDemoConfig)
    person_height_m: float = 1.95
    _procs: ProcessSupervisor | None = None
    _temp_keys: Path | None = None

    @classmethod
    def prepare(cls, n: int, out: str | Path, fleet: str = "gs-sim", radius_m: float = 8.0, altitude_m: float = 6.0,
                cameras: bool = True, keys_dir: str = "", mode: str = "orbit") -> "SimFleet":
        if n < 1:
            raise SkycapError(f"--sim {n}: the simulated fleet needs at least one drone")
        if mode not in ("orbit", "track"):
            raise SkycapError(f"simulated fleet mode {mode!r}: use 'orbit' or 'track' (--sim-mode)")
        if mode == "track" and not cameras:
            raise SkycapError("a simulated fleet in track mode needs the cameras: the drones find the person in them")
        ids = [f"drone_{i + 1}" for i in range(n)]
        flight = FlightFolder(out)
        if flight.has_recordings() or flight.summary_path.exists():
            raise SkycapError(f"{flight.path} already holds a flight; recordings are never overwritten: choose a new "
                              "flight folder")
        temp = None
        if not keys_dir:
            temp = Path(tempfile.mkdtemp(prefix="skycap-gs-keys-"))
            fk = FleetKeys.create(temp / "fleet", fleet, drones=ids, sim=True, days=2)
            keys_dir = str(fk.folder)
            log.info("simulated fleet: a temporary fleet CA in %s (mutual TLS + ACL; deleted at the end)", keys_dir)
        endpoint = f"tls/127.0.0.1:{free_tcp_port()}"
        return cls(ids=ids, out=flight.path, endpoint=endpoint, keys_dir=keys_dir, fleet=fleet, radius_m=radius_m,
                   altitude_m=altitude_m, cameras=cameras, mode=mode, _temp_keys=temp)

    @property
    def net_args(self) -> list[str]:
        return ["--zenoh-connect", self.endpoint, "--zenoh-keys", self.keys_dir]

    def spawn_ne_m(self) -> list[tuple[float, float]]:
        phases = evenly_spaced_phases(self.ids)
        return [(round(self.radius_m * math.cos(phases[d]), 3), round(self.radius_m * math.sin(phases[d]), 3))
                for d in self.ids]

    def start(self) -> None:
        """Start the simulator, the camera nodes and the agents (they join the rendezvous the app opened)."""
        flight = FlightFolder(self.out)
        flight.logs_dir.mkdir(parents=True, exist_ok=True)
        self._procs = ProcessSupervisor(flight.logs_dir)
        py = [sys.executable, "-m", "apps.cli"]
        base = free_udp_base(len(self.ids))
        spawn = ", ".join(f"[{n}, {e}]" for n, e in self.spawn_ne_m())
        look_down_deg = -math.degrees(math.atan2(self.altitude_m, self.radius_m))
        sim = py + ["sim", "--fleet", self.fleet, *self.net_args, "--truth-hz", "20", "--out",
                    str(flight.logs_dir / "sim"), "--status-every", "10", "--gimbal-pitch-deg", f"{look_down_deg:.2f}"]
        for s in [f"vehicles.count={len(self.ids)}", f"ports.offboard_base={base}", "ports.local_base=0",
                  "ports.gcs_port=0", f"vehicles.spawn_ne_m=[{spawn}]", *self.sim_set]:
            sim += ["--set", s]
        self._procs.start("sim", sim)
        if self.cameras:
            for d in self.ids:
                self._procs.start(f"camera_{d}", [sys.executable, "-m", "simulator.scene.node", "--drone-id", d,
                                                  "--fleet", self.fleet, *self.net_args])
        for i, d in enumerate(self.ids):
            self._procs.start(d, py + ["agent", "--drone-id", d, "--fleet", self.fleet, "--connection",
                                       f"udpin://0.0.0.0:{base + i}", "--record-dir", str(self.out), *self.net_args,
                                       *self.agent_set()])

    def agent_set(self) -> list[str]:
        """The agents' ``--set`` options for the mode (track: those ``skycap demo --mode track`` gives them with a
        GPS-grade estimate and the simulator's detections)."""
        if self.mode != "track":
            return []
        # the camera node tags each frame with the drone's latest published estimate: published often so that the
        # pose at capture is not stale while the drone turns
        return ["--set", "mode=track", "--set", "rates.state_publish_hz=25", "--set",
                "track.camera_position_sigma_m=1.0", "--set", f"track.person_height_m={self.person_height_m}",
                "--set", 'track.detections="sim"']

    def dead(self) -> dict[str, int]:
        """Processes that exited: {name: exit code}."""
        return self._procs.dead() if self._procs else {}

    def stop_agent(self, drone_id: str) -> None:
        """Stop one drone's agent (tests: a link that goes stale / lost)."""
        if self._procs:
            self._procs.stop([drone_id], timeout_s=10.0)

    def stop(self) -> None:
        if self._procs is not None:
            self._procs.stop([d for d in self.ids], timeout_s=20.0)  # agents first: they close their recordings
            self._procs.stop(None, timeout_s=10.0)
            self._procs = None
        if self._temp_keys is not None:
            shutil.rmtree(self._temp_keys, ignore_errors=True)
            self._temp_keys = None
