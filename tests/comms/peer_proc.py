"""A second OS process for the transport tests: a Zenoh peer that answers commands.

    python tests/comms/peer_proc.py ENDPOINT FLEET NODE

Joins the peer listening at ENDPOINT (explicit tcp/127.0.0.1 endpoint, multicast scouting off), subscribes
to the fleet's commands, declares its liveliness token, publishes 20 VehicleStates, then answers every
Command with a CommandAck. On action "disarm" it publishes a Health whose ``rates_hz`` carries its
subscription counters (received, malformed), then exits 0.
"""

from __future__ import annotations

import logging
import sys
import threading
import time

from comms.transport import Transport, TransportConfig
from shared_msgs import Command, CommandAck, Health, VehicleState, keys


def main() -> int:
    endpoint, fleet, node = sys.argv[1:4]
    logging.basicConfig(level=logging.WARNING, format=f"[{node}] %(levelname)s %(name)s: %(message)s")
    cfg = TransportConfig(listen=["tcp/127.0.0.1:0"], connect=[endpoint], multicast_scouting=False)
    done = threading.Event()
    with Transport.open(cfg, node_id=node) as bus:
        ack_key = keys.drone_key(fleet, node, keys.ACK)

        def on_cmd(rx) -> None:
            cmd: Command = rx.msg
            if cmd.action == "disarm":
                done.set()
                return
            ack = CommandAck(header=CommandAck.make_header(node), command_id=cmd.command_id, result="accepted")
            bus.publish(ack_key, ack)

        sub = bus.subscribe(keys.gcs_key(fleet, keys.CMD), on_cmd, expected_type=Command)
        bus.declare_alive(keys.alive_key(fleet, node))
        time.sleep(0.3)
        state_key = keys.drone_key(fleet, node, keys.STATE)
        for i in range(20):
            st = VehicleState(
                header=VehicleState.make_header(node),
                position_ned_m=(float(i), 0.0, -10.0),
                velocity_ned_m_s=(1.0, 0.0, 0.0),
                q_world_body=(1.0, 0.0, 0.0, 0.0),
                armed=True,
            )
            bus.publish(state_key, st)
            time.sleep(0.01)
        if not done.wait(30.0):
            print(f"[{node}] no disarm within 30 s", file=sys.stderr)
            return 3
        h = Health(
            header=Health.make_header(node),
            role="tool",
            state="done",
            rates_hz={"received": float(sub.stats.received), "malformed": float(sub.stats.malformed)},
        )
        bus.publish(keys.drone_key(fleet, node, keys.HEALTH), h)
        time.sleep(0.5)  # let it leave the socket before closing
    return 0


if __name__ == "__main__":
    sys.exit(main())
