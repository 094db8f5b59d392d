"""The same 3-drone orbit flown by the unchanged onboard agents on the built-in simulator and on real PX4 SITL (SIH),
each against its own truth: how well the built-in simulator predicts PX4 (issue 17).

    python bench/bench_sim_vs_px4.py [--drones 3] [--orbit-s 40] [--only sim,sim-noerr,sim-gps,px4] [--sim-set K=V ...]

One flight per row, one after the other, each with its own fleet and Zenoh rendezvous (tcp/127.0.0.1:7461, not the
default 7447), its own agents (``skycap agent``, MAVSDK) and the same plan: ``make_orbit_plan`` (radius 8 m,
6 m above the ground, 0.15 rad/s, centre at the world origin), drones spawned under their slots, take-off, plan,
start, ``--orbit-s`` of orbit, land. Rows:

* ``px4``: PX4 SITL instances 3.. (``simulator.px4_sitl.Px4Sitl(first_instance=3)``, homes under the slots) and
  SIH's true state (``SihTruthReader``); the agents' origin altitude is SIH's ground (489.4 m AMSL) so that
  "6 m" means the same height above the ground as on the simulator;
* ``sim``: the built-in simulator in this process (MAVLink on 14610+i, never 14540..14549) with SIH's airframe
  drag (``limits.drag_per_mass_1_s=1.0``: SIH_KDV 1 N/(m/s) on SIH_MASS 1 kg) and estimator errors of the size
  of SIH's EKF error (``SIH_LIKE_ESTIMATOR``, from this bench's ``est_err_*`` on PX4);
* ``sim-noerr``: the same with the estimator errors off (the control alone);
* ``sim-gps``: SIH's drag with the simulator's default estimator errors (a GPS-like ~1 m bias).

Figures over the steady orbit (plan start + ``--settle-s`` to the land command), true positions sampled at 20 Hz,
against the plan: radius RMS and mean radial bias (+ = outside), altitude RMS, phase RMS (angle about the centre
minus the slot angle: includes the fleet's common lag), mean phase (+ = ahead) and spacing RMS (phase with the
fleet's mean removed) -- per drone, then the fleet's mean row; and the vehicle's own estimate (the agent's
recording) against the truth: horizontal RMS, norm of the mean horizontal offset, vertical RMS. The machine is
printed with the table.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe_machine  # noqa: E402

log = logging.getLogger("bench_sim_vs_px4")

ORIGIN_LAT_DEG, ORIGIN_LON_DEG = 47.397742, 8.545594
SIM_GROUND_AMSL_M = 488.0  # the built-in simulator's default origin altitude (its ground)
SIH_GROUND_AMSL_M = 489.4  # SIH_LOC_H0
ZENOH_ENDPOINT = "tcp/127.0.0.1:7461"
SIM_OFFBOARD_BASE = 14610
PX4_FIRST_INSTANCE = 3
RADIUS_M, ALTITUDE_M, OMEGA_RAD_S = 8.0, 6.0, 0.15
#: the simulator's estimator errors set like SIH's EKF2 error measured by this bench (est_err_* of the px4 row,
#: 2026-11-26: ~0.12-0.19 m per horizontal axis, 0.1-0.6 m vertical, correlation times ~3 s)
SIH_LIKE_ESTIMATOR = {"pos_bias_std_xy_m": 0.15, "pos_bias_std_z_m": 0.3, "pos_bias_time_constant_s": 3.0}
RUNS = ("sim", "sim-noerr", "sim-gps", "px4")


class TruthSampler:
    """Samples ``read() -> (N, 3) world NED`` at ``rate_hz`` in a thread: (t_unix_s (T,), pos (N, T, 3))."""

    def __init__(self, read, rate_hz: float = 20.0):
        self._read, self._period = read, 1.0 / rate_hz
        self.t: list[float] = []
        self.p: list[np.ndarray] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="truth-sampler", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        nxt = time.time()
        while not self._stop.is_set():
            pos = self._read()
            if pos is not None:
                self.t.append(time.time())
                self.p.append(pos)
            nxt += self._period
            self._stop.wait(max(0.0, nxt - time.time()))

    def stop(self) -> tuple[np.ndarray, np.ndarray]:
        self._stop.set()
        self._thread.join(2.0)
        return np.array(self.t), np.stack(self.p, axis=1)


def orbit_figures(plan, ids: list[str], t_s: np.ndarray, pos: np.ndarray) -> dict[str, dict[str, float]]:
    """Per drone: radius RMS / mean bias, altitude RMS, phase RMS / mean, spacing RMS (see the module doc)."""
    from evaluation.flight import orbit_errors

    base = orbit_errors(plan, ids, t_s, pos)
    c = np.asarray(plan.center_ned_m, float)
    w = plan.direction * plan.angular_speed_rad_s
    t0 = plan.start_time_ns * 1e-9
    out = {}
    for k, d in enumerate(ids):
        rel = pos[k, :, :2] - c[:2]
        radial = np.hypot(rel[:, 0], rel[:, 1]) - plan.radius_m
        ang = np.arctan2(rel[:, 1], rel[:, 0])
        slot = plan.phase_offset_rad[d] + w * np.maximum(0.0, t_s - t0)
        ph = (ang - slot + np.pi) % (2 * np.pi) - np.pi
        out[d] = {"radius_rms_m": base[d]["orbit_radius_rmse_m"], "radial_bias_m": float(radial.mean()),
                  "alt_rms_m": base[d]["altitude_rmse_m"], "phase_rms_deg": base[d]["phase_error_deg_rms"],
                  "phase_mean_deg": float(np.degrees(np.mean(ph)) * plan.direction),
                  "spacing_rms_deg": base[d]["phase_spacing_error_deg_rms"]}
    return out


def estimate_figures(run_dir: Path, ids: list[str], t_s: np.ndarray, pos: np.ndarray) -> dict[str, dict[str, float]]:
    """Per drone, from the agent's recording (the vehicle's reported estimate, world NED) within the truth samples'
    time span: the estimate's error against the truth interpolated at each state's time -- horizontal RMS, mean
    horizontal offset (norm of the mean vector), vertical RMS."""
    from flightdata.flightlog import FlightLog
    from shared_msgs import VehicleState

    out = {}
    for k, d in enumerate(ids):
        files = sorted(run_dir.glob(f"{d}.s*.mcap"))
        states = [m for f in files for m in FlightLog(f).read_topic("state", VehicleState)]
        te = np.array([m.header.t_measurement_ns * 1e-9 for m in states])
        pe = np.array([m.position_ned_m for m in states])
        sel = (te >= t_s[0]) & (te <= t_s[-1])
        if sel.sum() < 10:
            out[d] = {"est_err_h_rms_m": math.nan, "est_err_h_mean_m": math.nan, "est_err_v_rms_m": math.nan}
            continue
        te, pe = te[sel], pe[sel]
        pt = np.stack([np.interp(te, t_s, pos[k, :, j]) for j in range(3)], axis=1)
        e = pe - pt
        out[d] = {"est_err_h_rms_m": float(np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2))),
                  "est_err_h_mean_m": float(np.hypot(*e[:, :2].mean(axis=0))),
                  "est_err_v_rms_m": float(np.sqrt(np.mean(e[:, 2] ** 2)))}
    return out


def _spawns_ne(ids: list[str]) -> list[tuple[float, float]]:
    from onboard.orbit import evenly_spaced_phases

    ph = evenly_spaced_phases(ids)
    return [(RADIUS_M * math.cos(ph[d]), RADIUS_M * math.sin(ph[d])) for d in ids]


def fly(kind: str, n: int, orbit_s: float, settle_s: float, workdir: Path, sim_set: list[str]) -> dict:
    """One flight; returns {"figures": {drone: {...}}, "samples": T, "note": str}."""
    from comms.transport import Transport, TransportConfig
    from groundstation.fleet import FleetClient, make_orbit_plan
    from onboard.orbit import evenly_spaced_phases
    from skycap.frames import ned_to_geodetic

    ids = [f"drone_{i + 1}" for i in range(n)]
    spawns = _spawns_ne(ids)
    fleet_id = f"b{kind.replace('-', '')}{uuid.uuid4().hex[:4]}"
    run_dir = workdir / kind
    run_dir.mkdir(parents=True, exist_ok=True)
    world = sitl = reader = None
    procs: list[subprocess.Popen] = []
    bus = Transport.open(TransportConfig.rendezvous(ZENOH_ENDPOINT), "bench")
    fleet = FleetClient(fleet_id, bus, heartbeat_hz=2.0)
    note = ""
    try:
        if kind == "px4":
            from simulator.px4_sitl import Px4Sitl, SihTruthReader

            homes = [tuple(float(x) for x in ned_to_geodetic(np.array([sn, se, 0.0]), ORIGIN_LAT_DEG, ORIGIN_LON_DEG,
                                                             SIH_GROUND_AMSL_M)[:2]) for sn, se in spawns]
            sitl = Px4Sitl(run_dir / "px4", n, first_instance=PX4_FIRST_INSTANCE, homes_geodetic=homes).start()
            reader = SihTruthReader([sitl.truth_port(k) for k in range(n)],
                                    (ORIGIN_LAT_DEG, ORIGIN_LON_DEG, SIH_GROUND_AMSL_M))
            urls = [sitl.connection_url(k) for k in range(n)]
            origin_alt = SIH_GROUND_AMSL_M

            def read():
                lt = reader.latest()
                return None if any(x is None for x in lt) else np.stack([x.position_ned_m for x in lt])
            note = f"PX4 SITL instances {PX4_FIRST_INSTANCE}..{PX4_FIRST_INSTANCE + n - 1} (SIH), truth = SIH state"
        else:
            from simulator.config import SimConfig
            from simulator.runner import SimWorld
            from skycap.config import load_config

            spawn = ", ".join(f"[{sn:.3f}, {se:.3f}]" for sn, se in spawns)
            over = [f"vehicles.count={n}", f"ports.offboard_base={SIM_OFFBOARD_BASE}", "ports.local_base=0",
                    "ports.gcs_port=0", f"vehicles.spawn_ne_m=[{spawn}]", "limits.drag_per_mass_1_s=1.0"]
            if kind == "sim":
                over += [f"estimator.{k}={v}" for k, v in SIH_LIKE_ESTIMATOR.items()]
            elif kind == "sim-noerr":
                over += ["estimator.pos_bias_std_xy_m=0", "estimator.pos_bias_std_z_m=0", "estimator.pos_noise_std_m=0",
                         "estimator.vel_noise_std_m_s=0", "estimator.att_noise_std_deg=0"]
            over += sim_set
            cfg = load_config(SimConfig, overrides=over)
            world = SimWorld(cfg).start_in_thread()
            urls = [f"udpin://0.0.0.0:{SIM_OFFBOARD_BASE + i}" for i in range(n)]
            origin_alt = cfg.origin.alt_m
            note = "built-in simulator (" + ", ".join(over[4:]) + "), truth = simulator state"

            def read():
                return np.stack([s.position_ned_m for s in world.truths()])
        for i, d in enumerate(ids):
            lf = open(run_dir / f"{d}.log", "w")
            cmd = [sys.executable, "-m", "apps.cli", "agent", "--drone-id", d, "--fleet", fleet_id, "--connection",
                   urls[i], "--record-dir", str(run_dir), "--zenoh-connect", ZENOH_ENDPOINT,
                   "--set", f"origin.alt_m={origin_alt}"]
            procs.append(subprocess.Popen(cmd, stdout=lf, stderr=subprocess.STDOUT, start_new_session=True, cwd=ROOT))
            lf.close()
        ok = fleet.wait_until(lambda f: all(d in f.states and f.states[d].health_ok and d in f.healths for d in ids),
                              90.0, "healthy drones")
        if not ok:
            raise RuntimeError(f"{kind}: drones not healthy within 90 s; see {run_dir}")
        acks = fleet.command("takeoff", wait_s=10, expect=ids, results=("accepted", "refused", "failed"))
        log.info("%s takeoff: %s", kind, acks)
        if not fleet.wait_until(lambda f: all(f.healths[d].state == "hover" for d in ids), 60.0, "hover"):
            raise RuntimeError(f"{kind}: not every drone hovering within 60 s; see {run_dir}")
        plan = make_orbit_plan(ids, (0.0, 0.0, 0.0), RADIUS_M, ALTITUDE_M, OMEGA_RAD_S, 1, start_in_s=2.0,
                               phase_offset_rad=evenly_spaced_phases(ids))
        fleet.send_plan(plan)
        fleet.wait_acks(plan.plan_id, ids, 5)
        fleet.command("start", wait_s=10, expect=ids, results=("accepted", "refused", "failed"))
        t_start = plan.start_time_ns * 1e-9
        sampler = TruthSampler(read, 20.0)
        while time.time() < t_start + orbit_s:
            if any(p.poll() is not None for p in procs):
                raise RuntimeError(f"{kind}: an agent exited; see {run_dir}")
            time.sleep(0.5)
        t, pos = sampler.stop()
        fleet.command("land", wait_s=10, expect=ids, results=("accepted", "refused", "failed"))
        fleet.wait_until(lambda f: all(f.healths[d].state == "landed" for d in ids), 40.0, "landed")
        win = (t >= t_start + settle_s) & (t <= t_start + orbit_s)
        np.savez(run_dir / "truth.npz", t_unix_s=t, pos_ned_m=pos, window=win)
        for p in procs:  # the agents close their recordings on SIGTERM
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            p.wait(20)
        figs = orbit_figures(plan, ids, t[win], pos[:, win])
        est = estimate_figures(run_dir, ids, t[win], pos[:, win])
        for d in ids:
            figs[d].update(est[d])
        if world is not None:  # a loaded machine: the simulation dropped backlog (its clock then lags the agents')
            note += f"; {world.overruns} times over 0.25 s behind real time"
        return {"figures": figs, "samples": int(win.sum()), "note": note}
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)
        fleet.close()
        bus.close()
        if reader is not None:
            reader.close()
        if sitl is not None:
            sitl.stop()
        if world is not None:
            world.stop()


COLS = ("radius_rms_m", "radial_bias_m", "alt_rms_m", "phase_rms_deg", "phase_mean_deg", "spacing_rms_deg",
        "est_err_h_rms_m", "est_err_h_mean_m", "est_err_v_rms_m")


def format_table(results: dict[str, dict]) -> str:
    head = f"{'run':10s} {'drone':8s} " + " ".join(f"{c:>16s}" for c in COLS)
    lines = [head, "-" * len(head)]
    for kind, r in results.items():
        figs = r["figures"]
        for d, row in figs.items():
            lines.append(f"{kind:10s} {d:8s} " + " ".join(f"{row[c]:16.3f}" for c in COLS))
        mean = {c: float(np.mean([row[c] for row in figs.values()])) for c in COLS}
        lines.append(f"{kind:10s} {'mean':8s} " + " ".join(f"{mean[c]:16.3f}" for c in COLS))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--drones", type=int, default=3)
    ap.add_argument("--orbit-s", type=float, default=40.0, help="seconds of orbit after the plan's start")
    ap.add_argument("--settle-s", type=float, default=8.0, help="seconds after the start left out of the figures")
    ap.add_argument("--only", default="sim,px4", help=f"comma-separated runs: {', '.join(RUNS)}")
    ap.add_argument("--sim-set", action="append", default=[], help="extra simulator override (repeatable)")
    ap.add_argument("--workdir", default="", help="where agents' logs/recordings and PX4's files go (default: temp)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    kinds = [k.strip() for k in args.only.split(",") if k.strip()]
    bad = [k for k in kinds if k not in RUNS]
    if bad:
        ap.error(f"unknown run(s) {bad}; use {', '.join(RUNS)}")
    workdir = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="bench_sim_vs_px4_"))
    results = {}
    for k in kinds:
        log.info("flight %s (%d drones, %.0f s orbit), files in %s", k, args.drones, args.orbit_s, workdir / k)
        results[k] = fly(k, args.drones, args.orbit_s, args.settle_s, workdir, args.sim_set)
        print(f"{k}: {results[k]['note']}; {results[k]['samples']} truth samples in the window", flush=True)
    print()
    print(f"orbit r={RADIUS_M} m, {ALTITUDE_M} m above ground, {OMEGA_RAD_S} rad/s, {args.drones} drones, "
          f"window = start+{args.settle_s:.0f} s .. start+{args.orbit_s:.0f} s; errors of the truth against the plan")
    print(format_table(results))
    print(f"machine: {describe_machine()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
