"""``skycap fleet ...``: send plans and commands to the fleet and watch it, over Zenoh.

    skycap fleet plan --drones drone_1,drone_2,drone_3 --radius 8 --altitude 6 --speed 0.15
    skycap fleet cmd takeoff                    # every drone
    skycap fleet cmd land --target drone_2
    skycap fleet watch                          # table of the fleet, and the ground-station heartbeat
    skycap gs [--sim N]                         # the ground-station app (PySide6)
    skycap gs --sim 3 --sim-mode track          # the simulated agents in track mode: plan a tracking formation
    skycap gs --selftest DIR                    # scripted offscreen operator session against a simulated fleet
    skycap gs --selftest DIR --sim-mode track   # the same with a tracking formation (person estimate, tracker)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fleet", help="fleet client: send a plan or commands, watch the fleet (over Zenoh)")
    p.add_argument("--fleet", default="default", help="fleet id (default: default)")
    p.add_argument("--zenoh-connect", default="tcp/127.0.0.1:7447", help="Zenoh endpoint to join")
    p.add_argument("--zenoh-keys", default=None, help="fleet folder from `skycap keys` (this ground station presents "
                   "its 'gcs' certificate; endpoints tls/...)")
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)

    pl = verbs.add_parser("plan", help="send an orbit plan (drones evenly spaced on one circle)")
    pl.add_argument("--drones", required=True, help="comma-separated drone ids in slot order, e.g. drone_1,drone_2")
    pl.add_argument("--center", default="0,0,0", help="orbit centre north,east,down in metres (default 0,0,0)")
    pl.add_argument("--radius", type=float, default=8.0, help="radius_m (default 8)")
    pl.add_argument("--altitude", type=float, default=6.0, help="altitude_m above ground (default 6)")
    pl.add_argument("--speed", type=float, default=0.15, help="angular speed rad/s (default 0.15)")
    pl.add_argument("--direction", type=int, choices=(1, -1), default=1, help="1 clockwise from above, -1 anti")
    pl.add_argument("--start-in", type=float, default=5.0, help="shared start time, seconds from now (default 5)")
    pl.add_argument("--min-separation", type=float, default=3.0, help="min_separation_m (default 3)")
    pl.add_argument("--mode", choices=("orbit", "track"), default=None,
                    help="say the plan's mode: orbit, or track (a tracking formation: --center is the person's start "
                         "guess, --radius the stand-off, no turning); agents of the other mode refuse it (default: "
                         "unsaid, each agent flies it in its own mode)")
    pl.add_argument("--wait", type=float, default=3.0, help="seconds to wait for the acks")
    pl.set_defaults(func=_plan)

    c = verbs.add_parser("cmd", help="send a fleet command and print the acks")
    c.add_argument("action", choices=["arm", "takeoff", "start", "pause", "land", "return", "disarm"])
    c.add_argument("--target", default="*", help="drone id, or * for every drone (default)")
    c.add_argument("--altitude", type=float, default=None, help="takeoff altitude_m")
    c.add_argument("--wait", type=float, default=3.0, help="seconds to wait for the acks")
    c.set_defaults(func=_cmd)

    w = verbs.add_parser("watch", help="print the fleet table every second (and send the ground-station heartbeat)")
    w.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0 = until Ctrl-C)")
    w.add_argument("--period", type=float, default=1.0, help="seconds between tables")
    w.set_defaults(func=_watch)
    register_gs(sub)


def _client(args, heartbeat_hz: float = 2.0):
    import time

    from groundstation.fleet import FleetClient
    from comms.transport import TransportConfig

    client = FleetClient.open(args.fleet, TransportConfig.local_peer(args.zenoh_connect, args.zenoh_keys or ""),
                              heartbeat_hz=heartbeat_hz)
    time.sleep(1.0)  # let Zenoh connect and the presence of the drones arrive
    return client


def _print_acks(acks, expect) -> int:
    bad = 0
    for d in sorted(set(expect) | set(acks)):
        a = acks.get(d)
        if a is None:
            print(f"{d}: no answer")
            bad += 1
        else:
            print(f"{d}: {a.result}{' - ' + a.reason if a.reason else ''}")
            bad += a.result in ("refused", "failed")
    return 1 if bad else 0


def _plan(args) -> int:
    from groundstation.fleet import make_orbit_plan

    center = tuple(float(x) for x in args.center.split(","))
    if len(center) != 3:
        print("--center must be north,east,down (three numbers)", file=sys.stderr)
        return 2
    ids = [d.strip() for d in args.drones.split(",") if d.strip()]
    speed = 0.0 if args.mode == "track" else args.speed
    plan = make_orbit_plan(ids, center, args.radius, args.altitude, speed, args.direction, args.start_in,
                           min_separation_m=args.min_separation, mode=args.mode or "")
    with _client(args) as fleet:
        fleet.send_plan(plan)
        acks = fleet.wait_acks(plan.plan_id, ids, args.wait, ("accepted", "refused"))
        return _print_acks(acks, ids)


def _cmd(args) -> int:
    params = {"altitude_m": args.altitude} if args.altitude is not None else {}
    with _client(args) as fleet:
        if args.target == "*":
            fleet.wait_until(lambda f: f.drones(), 2.0)  # health reports come at 2 Hz
        expect = [args.target] if args.target != "*" else fleet.drones()
        acks = fleet.command(args.action, args.target, params, wait_s=args.wait, expect=expect,
                             results=("accepted", "refused", "failed"))
        return _print_acks(acks, expect)


def _watch(args) -> int:
    import time

    with _client(args) as fleet:
        t_end = time.monotonic() + args.duration if args.duration > 0 else float("inf")
        while time.monotonic() < t_end:
            print(fleet.table(), flush=True)
            print(flush=True)
            time.sleep(args.period)
    return 0


# --------------------------------------------------------------------------------------------- skycap gs
def register_gs(sub: argparse._SubParsersAction) -> None:
    from skycap.config import add_config_args

    p = sub.add_parser("gs", help="the ground-station app (PySide6): plan, watch and command the fleet; process flights")
    p.add_argument("--sim", type=int, default=0, metavar="N",
                   help="start the built-in simulated fleet of N drones (temporary fleet CA, mutual TLS)")
    p.add_argument("--sim-mode", choices=("orbit", "track"), default="orbit",
                   help="the simulated agents' mode: orbit (default) or track (active capture: they find and follow "
                        "the person; plan a tracking formation)")
    p.add_argument("--selftest", type=Path, default=None, metavar="DIR",
                   help="run a scripted operator session offscreen against the simulated fleet (--sim N, default 2); "
                        "screenshots and DIR/selftest.json")
    p.add_argument("--orbit-s", type=float, default=20.0, help="self-test: seconds of orbit (default 20)")
    p.add_argument("--no-process", action="store_true", help="self-test: skip 'process flight'")
    add_config_args(p)
    p.set_defaults(func=_gs)


def _gs(args) -> int:
    import os

    from groundstation.app.config import GsConfig
    from skycap.config import config_from_args

    cfg = config_from_args(GsConfig, args)
    if args.selftest is not None:
        os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
        from groundstation.app.selftest import run_selftest

        report = run_selftest(args.selftest, drones=args.sim or 2, orbit_s=args.orbit_s, process=not args.no_process,
                              mode=args.sim_mode, cfg=cfg)
        for s in report["steps"]:
            print(f"{'ok  ' if s['ok'] else 'FAIL'} {s['name']}: {s['detail'][:160]}")
        print(f"self-test {'passed' if report.get('ok') else 'FAILED'}: {args.selftest / 'selftest.json'}")
        return 0 if report.get("ok") else 1
    from PySide6.QtWidgets import QApplication

    from groundstation.app.session import GsSession
    from groundstation.app.window import MainWindow

    import signal

    from PySide6.QtCore import QTimer

    app = QApplication.instance() or QApplication(["skycap gs"])
    session = GsSession.open(cfg, sim_drones=args.sim, sim_mode=args.sim_mode)
    try:
        win = MainWindow(session.model, session.cfg)
        win.show()
        # SIGINT / SIGTERM close the app like its window does (the simulated fleet stopped, the heartbeat ended);
        # the timer lets Python run its signal handlers while Qt's loop runs
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: app.quit())
        wake = QTimer()
        wake.timeout.connect(lambda: None)
        wake.start(300)
        return app.exec()
    finally:
        session.close()
