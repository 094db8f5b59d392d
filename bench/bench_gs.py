"""Benchmark: the ground-station app's own CPU with a live simulated fleet.

    python bench/bench_gs.py                  # 3 drones orbiting, 30 s measured (about 1.5 min in all)
    python bench/bench_gs.py --drones 3 --seconds 30 --idle   # drones on the ground

The app (fleet model + real Qt window, offscreen, its timers at the configured rates: fleet table / map 5 Hz,
thumbnails 1 Hz) runs in this process; the simulated fleet (simulator, cameras, agents) in child processes.
Measured: this process's CPU time (every thread: Qt, Zenoh, the heartbeat) over the window, as % of one core,
once with the Live view tab shown (thumbnails decoded), once with the 3D tab (repainted at the table's 5 Hz, only
while shown) and once with the Map tab (thumbnails not decoded).
Target: <= 25 % of one core. Prints a table with the machine noted.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

from bench._machine import describe_machine  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drones", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=30.0, help="measured window per view (default 30)")
    ap.add_argument("--idle", action="store_true", help="drones stay on the ground (default: take off and orbit)")
    args = ap.parse_args()

    from PySide6.QtWidgets import QApplication

    from groundstation.app.config import GsConfig
    from groundstation.app.model import PlanForm
    from groundstation.app.selftest import pump, pump_until
    from groundstation.app.session import GsSession
    from groundstation.app.window import MainWindow
    from skycap.logsetup import setup_logging

    setup_logging("WARNING")
    app = QApplication.instance() or QApplication(["bench_gs"])
    tmp = Path(tempfile.mkdtemp(prefix="bench-gs-"))
    cfg = GsConfig(flights_dir=str(tmp))
    session = GsSession.open(cfg, sim_drones=args.drones, sim_out=tmp / "flight")
    win = MainWindow(session.model, session.cfg)
    win.resize(1500, 900)
    win.show()
    ids, c, m = session.sim.ids, session.client, session.model
    rows = []
    try:
        if not pump_until(lambda: all(d in c.states and c.states[d].health_ok and d in c.healths for d in ids), 150):
            print(f"drones not healthy: dead processes {session.sim.dead()}", file=sys.stderr)
            return 1
        load = "on the ground"
        if not args.idle:
            m.send_plan(PlanForm(radius_m=8.0, altitude_m=6.0, speed_m_s=1.2, drones=ids))
            m.command("takeoff", ids)
            if not pump_until(lambda: all(c.healths[d].state == "hover" for d in ids), 60):
                print("the drones did not reach hover", file=sys.stderr)
                return 1
            m.command("start", ids)
            pump_until(lambda: all(c.healths[d].state == "orbit" for d in ids), 20)
            load = "orbiting"
        for tab in ("Live view", "3D", "Map / plan"):
            win.show_tab(tab)
            pump(2.0)
            dec0, thumbs0 = win.thumbs.decoded, sum(m.thumb_count.values())
            t0, c0 = time.monotonic(), time.process_time()
            la0 = os.getloadavg()[0]
            pump(args.seconds)
            cpu = 100.0 * (time.process_time() - c0) / (time.monotonic() - t0)
            rows.append((tab, load, cpu, sum(m.thumb_count.values()) - thumbs0, win.thumbs.decoded - dec0,
                         (la0 + os.getloadavg()[0]) / 2))
        if not args.idle:
            m.land_all()
            pump_until(lambda: all(c.healths[d].state in ("landed", "idle") for d in ids), 40)
    finally:
        win.close()
        session.close()
    print(f"\nground-station app CPU, {args.drones} simulated drones ({describe_machine()})")
    print(f"UI rates: table/map/3D {cfg.ui.table_hz:g} Hz, thumbnails {cfg.ui.thumbs_hz:g} Hz; window {args.seconds:g} s per view\n")
    print(f"{'view':12s} {'drones':14s} {'app CPU % of one core':>22s} {'thumbs rx':>10s} {'decoded':>8s} {'load avg':>9s}")
    for tab, load, cpu, rx, dec, la in rows:
        print(f"{tab:12s} {load:14s} {cpu:22.1f} {rx:10d} {dec:8d} {la:9.2f}")
    worst = max(r[2] for r in rows)
    print(f"\ntarget <= 25 % of one core: {'met' if worst <= 25 else 'NOT met'} (worst {worst:.1f} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
