"""A hostile outsider for fault tests: a node without the fleet's certificate tries to join, snoop and command.

    probe = OutsiderProbe("127.0.0.1:7447", fleet="demo", workdir=tmp)   # opens its sessions
    probe.tick(time.time())          # call often: sends a 'land' to every drone every period_s
    report = probe.close()           # links it got, messages it received, commands it sent

Two attempts, both as the ground station (``sender_id`` "gcs"):

* ``plain``: plaintext ``tcp/<address>`` (what anyone on the network would try first);
* ``foreign_ca``: mutual TLS on ``tls/<address>`` with a certificate named ``gcs`` from *another* CA (made here,
  in ``workdir``): it knows the names, not the fleet's keys.

Each subscribes to ``skycap/v1/<fleet>/**`` and counts every sample it gets (whatever it decodes to) and
publishes ``land`` commands for every drone on the ground station's key. Against a secure fleet it must get no
link, receive nothing, and no drone may answer (``command_ids`` lets the caller look for acks).
"""

from __future__ import annotations

import logging
import threading
import uuid
from pathlib import Path

from comms.security import FleetKeys
from comms.transport import Transport, TransportConfig
from shared_msgs import Command, keys

log = logging.getLogger(__name__)

__all__ = ["OutsiderProbe"]


class OutsiderProbe:
    """An outsider's two sessions against the rendezvous at ``address`` (``host:port``)."""

    def __init__(self, address: str, fleet: str, workdir: str | Path, period_s: float = 0.5):
        self.fleet, self.period_s = fleet, period_s
        foreign = FleetKeys.create(Path(workdir) / "outsider-keys", fleet, drones=[])
        cfgs = {"plain": TransportConfig(listen=[], connect=[f"tcp/{address}"]),
                "foreign_ca": TransportConfig.local_peer(f"tls/{address}", str(foreign.folder))}
        self._lock = threading.Lock()
        self.received = {name: 0 for name in cfgs}
        self.commands_sent = 0
        self.command_ids: list[str] = []
        self._own: set[str] = set()
        self.links_seen = {name: 0 for name in cfgs}
        self.sessions: dict[str, Transport] = {}
        self._t_next = 0.0
        for name, cfg in cfgs.items():
            bus = Transport.open(cfg, f"outsider-{name}", identity=keys.GCS)
            bus.subscribe(f"{keys.PREFIX}/{fleet}/**", lambda rx, n=name: self._count(n, rx))
            self.sessions[name] = bus
        log.warning("FAULT: an outsider (no fleet certificate: plaintext, and a foreign CA's 'gcs') joins %s", address)

    def _count(self, name: str, rx) -> None:
        with self._lock:
            if getattr(rx.msg, "command_id", None) in self._own:
                return  # its own command, delivered to its own subscriber by Zenoh
            self.received[name] += 1

    def tick(self, now_s: float) -> None:
        """Send a 'land' for every drone from each session every ``period_s``; note any link it got."""
        if now_s < self._t_next:
            return
        self._t_next = now_s + self.period_s
        for name, bus in self.sessions.items():
            self.links_seen[name] = max(self.links_seen[name], len(bus.peers()))
            cid = f"outsider-land-{uuid.uuid4().hex[:8]}"
            with self._lock:
                self._own.add(cid)
            try:
                bus.publish(keys.gcs_key(self.fleet, keys.CMD),
                            Command(header=Command.make_header(keys.GCS), command_id=cid, target="*", action="land"))
            except Exception as e:  # nothing to publish to is fine: the point is that it cannot
                log.debug("outsider publish failed: %s", e)
            self.command_ids.append(cid)
            self.commands_sent += 1

    def close(self) -> dict:
        """Close the sessions; the report: links (peers) each got, fleet messages each received (its own commands
        excluded), commands sent."""
        for bus in self.sessions.values():
            bus.close()
        with self._lock:
            return {"links": dict(self.links_seen), "received": dict(self.received),
                    "commands_sent": self.commands_sent}
