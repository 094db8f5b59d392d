"""``skycap agent``: run one drone's onboard agent (one process per drone, as on its companion computer)."""

from __future__ import annotations

import argparse

from skycap.config import add_config_args


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "agent",
        help="run a drone's onboard agent (autopilot over MAVSDK, fleet over Zenoh, MCAP recording)",
        description="Run one drone's onboard agent until SIGTERM/SIGINT (then it lands if airborne, as "
        "configured by safety.sigterm_action, and closes its recording). Example: skycap agent --drone-id "
        "drone_2 --connection udpin://0.0.0.0:14541 --record-dir flights/f1",
    )
    add_config_args(p)
    p.add_argument("--drone-id", default=None, help="this drone's id (drone_1, drone_2 ...)")
    p.add_argument("--fleet", default=None, help="fleet id (the Zenoh key segment shared with the ground station)")
    p.add_argument("--connection", default=None, help="MAVSDK connection URL, e.g. udpin://0.0.0.0:14540")
    p.add_argument("--record-dir", default=None, help="flight folder; each agent start records a new sortie <dir>/<drone_id>.s<NNN>.mcap")
    p.add_argument("--no-record", action="store_true", help="do not record an MCAP file")
    p.add_argument("--zenoh-connect", default=None, help="Zenoh endpoint to join, e.g. tls/127.0.0.1:7447")
    p.add_argument("--zenoh-keys", default=None, help="fleet folder from `skycap keys` (transport.security.keys_dir)")
    p.add_argument("--print-config", action="store_true", help="print the resolved configuration (TOML) and exit")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import asyncio

    from comms.transport import local_peer_overrides
    from onboard.agent import run_agent
    from onboard.config import AgentConfig
    from skycap.config import config_from_args

    extra = {
        "drone_id": args.drone_id,
        "fleet": args.fleet,
        "connection": args.connection,
        "record.dir": args.record_dir,
        "record.enabled": False if args.no_record else None,
        **local_peer_overrides(args.zenoh_connect, args.zenoh_keys),
    }
    cfg = config_from_args(AgentConfig, args, extra).validate()
    if args.print_config:
        import tomli_w

        from skycap.config import config_to_dict

        print(tomli_w.dumps(config_to_dict(cfg)))
        return 0
    return asyncio.run(run_agent(cfg))
