"""``skycap sim``: run the built-in simulator's vehicles (PX4-SITL-compatible MAVLink) until SIGINT/SIGTERM.

skycap sim --drones 3                                   # vehicles 1..3 -> udp 14540..14542, GCS 14550
skycap sim --drones 1 --set wind.mean_speed_m_s=5 --set battery.start_percent=20
skycap sim --config sim.toml --duration 60
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
from pathlib import Path

from skycap.config import add_config_args, config_from_args, save_config

log = logging.getLogger("simulator")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sim",
        help="run simulated PX4 multirotors (MAVLink over UDP, like PX4 SITL)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--drones", type=int, default=None, help="number of vehicles (vehicles.count)")
    p.add_argument(
        "--duration", type=float, default=None, help="stop after this many seconds (default: run until Ctrl-C)"
    )
    p.add_argument("--out", type=Path, default=None, help="write the resolved config.toml into this folder")
    p.add_argument(
        "--status-every", type=float, default=10.0, help="log each vehicle's state every N seconds (0: never)"
    )
    add_config_args(p)
    p.set_defaults(func=run_sim)


def run_sim(args: argparse.Namespace) -> int:
    from simulator.config import SimConfig
    from simulator.runner import SimWorld

    cfg = config_from_args(SimConfig, args, extra={"vehicles.count": args.drones}).validate()
    if args.out is not None:
        path = save_config(cfg, Path(args.out) / "config.toml")
        log.info("resolved configuration written to %s", path)
    world = SimWorld(cfg)

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(
                sig, lambda s=sig: (log.info("%s received, stopping", signal.Signals(s).name), stop.set())
            )
        await world.run(stop, duration_s=args.duration, status_every_s=args.status_every)

    o = cfg.origin
    log.info(
        "origin %.6f, %.6f, %.1f m AMSL; %d vehicle(s): system ids 1..%d, offboard/API links -> %s:%d..%d%s",
        o.lat_deg,
        o.lon_deg,
        o.alt_m,
        cfg.vehicles.count,
        cfg.vehicles.count,
        cfg.ports.host,
        cfg.ports.offboard_base,
        cfg.ports.offboard_base + cfg.vehicles.count - 1,
        f", ground station -> {cfg.ports.host}:{cfg.ports.gcs_port}" if cfg.ports.gcs_port else "",
    )
    asyncio.run(main())
    for line in world.status_lines():
        log.info("final: %s", line)
    log.info("simulator stopped after %.1f s (%d ticks, %d overruns)", world.t_s, world.ticks, world.overruns)
    return 0
