"""The app's network session: the rendezvous the drones connect to (``gcs`` identity), the fleet client with its
heartbeat, the fleet model and, with ``--sim N``, the built-in simulated fleet. No Qt."""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

from comms.transport import Transport, TransportConfig
from groundstation.app.config import GsConfig
from groundstation.app.model import FleetModel
from groundstation.fleet import FleetClient
from groundstation.simfleet import SimFleet
from shared_msgs import keys
from skycap.errors import SkycapError

log = logging.getLogger(__name__)

__all__ = ["GsSession"]


class GsSession:
    def __init__(self, cfg: GsConfig, sim: SimFleet | None = None):
        self.cfg = cfg.validate()
        self.sim = sim
        net = cfg.network
        if not net.keys_dir and net.endpoint.startswith(("tls/", "quic/")):
            raise SkycapError(f"network.endpoint {net.endpoint} is TLS but network.keys_dir is empty: set "
                              "--set network.keys_dir=DIR (the fleet folder made by `skycap keys`; the app presents "
                              "its 'gcs' certificate), or for an INSECURE debugging session a tcp/ endpoint")
        if net.keys_dir:
            from comms.security import FleetKeys

            fleet_keys = FleetKeys.load(net.keys_dir)
            if fleet_keys.fleet != cfg.fleet:
                raise SkycapError(f"network.keys_dir {net.keys_dir} is the fleet folder of {fleet_keys.fleet!r}, the app "
                                  f"is set to fleet {cfg.fleet!r}: pass --set fleet=\"{fleet_keys.fleet}\" (or the "
                                  "fleet folder of the right fleet)")
            fleet_keys.check(keys.GCS)
        if not net.keys_dir:
            log.warning("INSECURE ground station (network.keys_dir empty): plaintext Zenoh, no certificates, no access "
                        "control. Make a fleet folder with `skycap keys` and set network.keys_dir.")
        self.bus = Transport.open(TransportConfig.rendezvous(net.endpoint, net.keys_dir), "gs", identity=keys.GCS)
        self.client = FleetClient(cfg.fleet, self.bus, heartbeat_hz=net.heartbeat_hz)
        self.model = FleetModel(self.client, cfg)
        log.info("ground station listening on %s for fleet %r", net.endpoint, cfg.fleet)

    @classmethod
    def open(cls, cfg: GsConfig, sim_drones: int = 0, sim_out: str | Path | None = None,
             sim_cameras: bool = True, sim_mode: str = "orbit") -> "GsSession":
        """Open the listener; with ``sim_drones`` > 0, first prepare the simulated fleet (its temporary CA and
        endpoint replace the configured ones; its agents in ``sim_mode``: "orbit" or "track") and start its
        processes once the listener is open."""
        sim = None
        if sim_drones > 0:
            out = sim_out or Path(cfg.flights_dir) / time.strftime("gs-sim-%Y%m%d-%H%M%S", time.gmtime())
            sim = SimFleet.prepare(sim_drones, out, fleet=cfg.fleet if cfg.fleet != "default" else "gs-sim",
                                   cameras=sim_cameras, mode=sim_mode)
            cfg = dataclasses.replace(cfg, fleet=sim.fleet, network=dataclasses.replace(
                cfg.network, endpoint=sim.endpoint, keys_dir=sim.keys_dir))
        s = cls(cfg, sim)
        if sim is not None:
            try:
                sim.start()
            except Exception:
                s.close()
                raise
            s.model.log_event("info", "", f"simulated fleet of {sim_drones} started ({sim.mode} mode), "
                                      f"recording into {sim.out}")
        return s

    def close(self) -> None:
        self.model.close()
        if self.sim is not None:
            self.sim.stop()
        self.client.close()
        self.bus.close()
