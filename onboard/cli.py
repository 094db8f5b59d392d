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
    p.add_argument("--standby", action="store_true",
                   help="a warm spare: load everything, then wait for SIGUSR1 before starting (a supervisor wakes it "
                        "when the drone's agent died: it takes over in a fraction of the ~1-3 s a cold start takes, "
                        "the recording time lost in between)")
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
    if args.standby:
        _wait_to_take_over(cfg.drone_id)
    return asyncio.run(run_agent(cfg))


def _wait_to_take_over(drone_id: str) -> None:
    """``--standby``: everything is imported and configured; wait for SIGUSR1 (SIGTERM still ends the process)."""
    import logging
    import os
    import signal
    import time

    import onboard.agent.process  # noqa: F401  (imported by run_agent already: the spare's point is to have it)

    log = logging.getLogger(__name__)
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGUSR1})
    log.info("%s: standby agent ready (pid %d); waiting for SIGUSR1 to take over", drone_id, os.getpid())
    signal.sigwait({signal.SIGUSR1})
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGUSR1})
    log.warning("%s: standby agent taking over at %.3f", drone_id, time.time())
