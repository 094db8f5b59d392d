"""``skycap sim``: run the built-in simulator's vehicles (PX4-SITL-compatible MAVLink) until SIGINT/SIGTERM.

skycap sim --drones 3                                   # vehicles 1..3 -> udp 14540..14542, GCS 14550
skycap sim --drones 1 --set wind.mean_speed_m_s=5 --set battery.start_percent=20
skycap sim --config sim.toml --duration 60
skycap sim --drones 3 --fleet demo --zenoh-connect tcp/127.0.0.1:7447   # + ground truth on the fleet's sim/truth
skycap sim --fleet demo --motion cmu/005/005_10.bvh --set motion.end=clamp   # a recorded motion

``--motion FILE.bvh`` (``motion.file``): the simulated person performs that recorded motion (any CMU-style BVH,
placed at ``motion.center_ne_m`` on the ground, looped or clamped: :mod:`simulator.scene.person`) instead of the
default walk with stops; the file is read (and a bad one refused) before anything starts.

With ``--fleet``, the simulator joins the fleet's Zenoh network and publishes the ground truth (every vehicle's
true pose and the simulated person's joints, ``SimTruth`` on ``sim/truth``, :mod:`simulator.truth`) and takes
the simulator-side fault schedule (``--gps-jump``, ``--param-at``). The demo launches it this way.

``--autopilot px4``: instead of the built-in vehicles, real PX4 SITL with PX4's SIH simulator
(:mod:`simulator.px4_sitl`; the build from ``--px4-dir``, default ``../shared/px4-sitl`` beside the checkout):

skycap sim --autopilot px4 --drones 2 --px4-first-instance 6 --fleet demo --zenoh-connect tcp/127.0.0.1:7447

starts ``--drones`` PX4 instances numbered from ``--px4-first-instance`` (instance i: MAVLink udpin 14540+i,
so the agents connect to ``udpin://0.0.0.0:<14540+i>``; the built-in ``ports.*`` settings do not apply), each
at home = its ``vehicles.spawn_ne_m`` position converted to geodetic about ``origin``, and with ``--fleet``
publishes SimTruth from SIH's true states (:mod:`simulator.px4_truth`: resampled at ``--truth-hz``; gimbal pitch
= the fixed ``--gimbal-pitch-deg``, SIH has no gimbal; the same simulated person). ``--param-at`` sets the PX4
parameter through PX4's shell; ``--gps-jump`` is refused (PX4's estimator cannot be offset from outside).
SIGINT/SIGTERM stop PX4 cleanly. PX4's consoles and logs go to ``<--out>/px4/instance_<i>/`` (``--out``
given; ``px4.2``, ``px4.3``, ... when an earlier run's folder is there) or a temporary folder.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import math
import signal
from pathlib import Path

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from skycap.config import add_config_args, config_from_args, save_config
from skycap.errors import SkycapError

if TYPE_CHECKING:
    from simulator.config import SimConfig

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
    p.add_argument("--motion", default=None, metavar="FILE.bvh",
                   help="the person performs this recorded motion (a CMU-style BVH; motion.* settings)")
    p.add_argument(
        "--status-every", type=float, default=10.0, help="log each vehicle's state every N seconds (0: never)"
    )
    ap = p.add_argument_group("autopilot")
    ap.add_argument("--autopilot", choices=("builtin", "px4"), default="builtin",
                    help="builtin (default): the project's simulated vehicles; px4: real PX4 SITL with SIH")
    ap.add_argument("--px4-dir", default=None,
                    help="the PX4 SITL build (bin/px4, modules.txt, etc/); default ../shared/px4-sitl beside the "
                         "checkout or $SKYCAP_PX4_SITL")
    ap.add_argument("--px4-first-instance", type=int, default=0,
                    help="PX4 instance number of the first vehicle (instance i uses MAVLink UDP 14540+i; 0..9)")
    net = p.add_argument_group("ground truth on the fleet network")
    net.add_argument("--fleet", default=None, help="publish the ground truth on this fleet's sim/truth key (Zenoh)")
    net.add_argument("--zenoh-connect", default="tcp/127.0.0.1:7447", help="Zenoh endpoint to join")
    net.add_argument("--zenoh-keys", default=None, help="fleet folder from `skycap keys` (the simulator presents "
                     "the 'sim' certificate; endpoints tls/...)")
    net.add_argument("--truth-hz", type=float, default=50.0, help="ground-truth publishing rate")
    net.add_argument("--gimbal-pitch-deg", type=float, default=None,
                     help="the pitch each vehicle's gimbal starts at (gimbal.initial_pitch_deg; without a gimbal: the "
                          "fixed camera pitch reported in the truth)")
    net.add_argument("--gps-jump", default=None, metavar="INDEX,AT_S,N,E,D",
                     help="fault injection: vehicle INDEX's position estimate jumps by (N, E, D) m AT_S seconds after "
                          "the start time of the first orbit plan seen on the fleet's plan key")
    net.add_argument("--param-at", action="append", default=[], metavar="INDEX,AT_S,NAME,VALUE",
                     help="set vehicle INDEX's autopilot parameter NAME to VALUE AT_S seconds after the start time of "
                          "the first orbit plan (e.g. COM_OBL_RC_ACT=4: land on offboard loss); repeatable")
    net.add_argument("--link-loss", action="append", default=[], metavar="INDEX,AT_S,FOR_S",
                     help="fault injection: vehicle INDEX's offboard MAVLink link carries nothing (either way) for "
                          "FOR_S seconds from AT_S seconds after the first orbit plan's start time; repeatable")
    add_config_args(p)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from simulator.config import SimConfig  # imported here: `skycap --help` imports every command module

    extra = {"vehicles.count": args.drones, "motion.file": str(Path(args.motion).resolve()) if args.motion else None}
    if args.gimbal_pitch_deg is not None:
        extra["gimbal.initial_pitch_deg"] = args.gimbal_pitch_deg
    cfg = config_from_args(SimConfig, args, extra=extra).validate()
    if args.autopilot == "builtin" and (args.px4_dir or args.px4_first_instance):
        raise SkycapError("--px4-dir and --px4-first-instance are for --autopilot px4")
    if args.autopilot == "px4" and args.link_loss:
        raise SkycapError("--link-loss acts on the built-in simulator's vehicle link; leave it out with --autopilot px4")
    if args.autopilot == "px4" and args.gps_jump:
        raise SkycapError("--gps-jump acts on the built-in simulator's estimator; PX4's cannot be offset from "
                          "outside: leave it out with --autopilot px4 (or use --autopilot builtin)")
    if cfg.motion.file:  # read it now: a file the person cannot play is an error before anything starts
        from simulator.scene.person import load_bvh_motion

        load_bvh_motion(cfg.motion)
    net = None
    if args.fleet:
        net = SimNetwork(fleet=args.fleet, zenoh_connect=args.zenoh_connect, zenoh_keys=args.zenoh_keys or "",
                         truth_hz=args.truth_hz,
                         gimbal_pitch_rad=math.radians(args.gimbal_pitch_deg or 0.0),
                         gps_jump=args.gps_jump, param_at=list(args.param_at), link_loss=list(args.link_loss))
    elif args.gps_jump or args.param_at or args.link_loss:
        raise SkycapError("--gps-jump, --param-at and --link-loss act on the fleet's plan: give --fleet too")
    if args.autopilot == "px4":
        return run_px4(cfg, px4_dir=args.px4_dir, first_instance=args.px4_first_instance, out=args.out,
                       duration_s=args.duration, status_every_s=args.status_every, net=net)
    return run_sim(cfg, out=args.out, duration_s=args.duration, status_every_s=args.status_every, net=net)


@dataclass
class SimNetwork:
    """The simulator on the fleet's network: ground truth publishing and the fault schedule."""

    fleet: str
    zenoh_connect: str = "tcp/127.0.0.1:7447"
    zenoh_keys: str = ""  #: fleet folder (mutual TLS + ACL as the 'sim' identity); '' = insecure
    truth_hz: float = 50.0
    gimbal_pitch_rad: float = 0.0
    gps_jump: str | None = None
    param_at: list[str] = field(default_factory=list)
    link_loss: list[str] = field(default_factory=list)


def run_sim(cfg: SimConfig, out: Path | None = None, duration_s: float | None = None, status_every_s: float = 10.0,
            net: SimNetwork | None = None) -> int:
    """Run the simulator until SIGINT/SIGTERM (or ``duration_s``); with ``net``, also on the fleet network."""
    # imported here: `skycap --help` imports every command module, and these pull in Zenoh and pymavlink
    from comms.transport import Transport, TransportConfig
    from shared_msgs import keys
    from simulator.runner import SimWorld
    from simulator.truth import SimFaults, TruthPublisher, schedule_faults

    if out is not None:
        path = save_config(cfg, Path(out) / "config.toml")
        log.info("resolved configuration written to %s", path)
    world = SimWorld(cfg)
    bus = None
    if net is not None:
        faults = SimFaults.parse(net.gps_jump, net.param_at, len(world.vehicles),
                                 lambda name: world.vehicles[0].params.get(name) is not None, net.link_loss)
        bus = Transport.open(TransportConfig.local_peer(net.zenoh_connect, net.zenoh_keys), "sim")
        bus.declare_alive(keys.alive_key(net.fleet, keys.SIM))
        TruthPublisher(world, bus, net.fleet, rate_hz=net.truth_hz, gimbal_pitch_rad=net.gimbal_pitch_rad,
                       motion=cfg.motion)
        schedule_faults(world, bus, net.fleet, faults)

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(
                sig, lambda s=sig: (log.info("%s received, stopping", signal.Signals(s).name), stop.set())
            )
        await world.run(stop, duration_s=duration_s, status_every_s=status_every_s)

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
    try:
        asyncio.run(main())
    finally:
        if bus is not None:
            bus.close()
    for line in world.status_lines():
        log.info("final: %s", line)
    log.info("simulator stopped after %.1f s (%d ticks, %d overruns)", world.t_s, world.ticks, world.overruns)
    return 0


def run_px4(cfg: SimConfig, px4_dir: str | None = None, first_instance: int = 0, out: Path | None = None,
            duration_s: float | None = None, status_every_s: float = 10.0, net: SimNetwork | None = None) -> int:
    """Run ``cfg.vehicles.count`` PX4 SITL (SIH) instances until SIGINT/SIGTERM (or ``duration_s``); with ``net``,
    publish SIH's truth and apply the parameter schedule (see the module doc)."""
    import tempfile
    import threading
    import time

    from simulator.px4_sitl import Px4Sitl, find_px4_folder
    from skycap.frames import ned_to_geodetic

    folder = find_px4_folder(px4_dir)  # clear error naming --px4-dir when PX4 is absent
    if out is not None:
        path = save_config(cfg, Path(out) / "config.toml")
        log.info("resolved configuration written to %s", path)
    o = cfg.origin
    n = cfg.vehicles.count
    homes = []
    for k in range(n):
        lat, lon, _ = ned_to_geodetic(cfg.spawn_ned_m(k), o.lat_deg, o.lon_deg, o.alt_m)
        homes.append((float(lat), float(lon)))
    tmp = None
    if out is not None:
        # PX4 makes each instance's folder fresh: never reuse one that holds an earlier run's consoles and logs
        workdir = Path(out) / "px4"
        n_run = 1
        while workdir.exists():
            n_run += 1
            workdir = Path(out) / f"px4.{n_run}"
    else:
        tmp = tempfile.TemporaryDirectory(prefix="skycap-px4-")
        workdir = Path(tmp.name)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda s, _f: (log.info("%s received, stopping PX4", signal.Signals(s).name), stop.set()))
    sitl = Px4Sitl(workdir, n, folder=folder, first_instance=first_instance, homes_geodetic=homes)
    bus = publisher = cancel = None
    t_begin = time.monotonic()
    try:
        sitl.start()
        log.info("PX4 SITL (SIH) from %s: %d vehicle(s), instances %d..%d, agents connect to %s; consoles in %s",
                 folder, n, first_instance, first_instance + n - 1,
                 ", ".join(sitl.connection_url(k) for k in range(n)), workdir)
        if net is not None:
            from comms.transport import Transport, TransportConfig
            from shared_msgs import keys
            from simulator.px4_truth import (SihTruthPublisher, px4_param_name_ok, read_px4_param,
                                             schedule_px4_params)
            from simulator.truth import SimFaults

            faults = SimFaults.parse(None, net.param_at, n, px4_param_name_ok)
            ground = read_px4_param(sitl, 0, "SIH_LOC_H0")
            log.info("SIH ground (SIH_LOC_H0): %s m AMSL; world origin %.6f, %.6f, %.1f m AMSL", ground, o.lat_deg,
                     o.lon_deg, o.alt_m)
            bus = Transport.open(TransportConfig.local_peer(net.zenoh_connect, net.zenoh_keys), "sim")
            bus.declare_alive(keys.alive_key(net.fleet, keys.SIM))
            publisher = SihTruthPublisher(bus, net.fleet, [sitl.truth_port(k) for k in range(n)],
                                          (o.lat_deg, o.lon_deg, o.alt_m), rate_hz=net.truth_hz,
                                          gimbal_pitch_rad=net.gimbal_pitch_rad, ground_alt_amsl_m=ground,
                                          motion=cfg.motion)
            cancel = schedule_px4_params(sitl, bus, net.fleet, faults)
        t_status = time.monotonic() + status_every_s if status_every_s > 0 else math.inf
        while not stop.is_set():
            if duration_s is not None and time.monotonic() - t_begin >= duration_s:
                break
            dead = [sitl.instance(k) for k, a in enumerate(sitl.alive()) if not a]
            if dead:
                raise SkycapError(f"PX4 SITL instance(s) {dead} exited; see their consoles in {workdir}")
            if time.monotonic() >= t_status:
                t_status += status_every_s
                msg = publisher.message(time.time_ns()) if publisher is not None else None
                for k, v in enumerate(msg.vehicles if msg is not None else []):
                    log.info("%s: truth NED %s m (%d SIH samples); %d truths published", v.drone_id,
                             [round(x, 2) for x in v.position_ned_m], publisher.reader.counts[k], publisher.published)
            stop.wait(0.2)
    finally:
        if cancel is not None:
            cancel.set()
        if publisher is not None:
            publisher.close()
        if bus is not None:
            bus.close()
        sitl.stop()
        if tmp is not None:
            tmp.cleanup()
    log.info("PX4 SITL stopped after %.1f s", time.monotonic() - t_begin)
    return 0
