"""Benchmark: cooperative filter update time and formation MPC solve times (3, 5, 8 drones), warm-started.

    python bench/bench_tracking.py [--steps 150] [--quick]

The MPC runs closed loop in lockstep: every drone plans against its teammates' plans of the previous step
and then flies its setpoint exactly; the person walks. Solve time is the wall time of the solver call
(CasADi -> OSQP / qpOASES / IPOPT) as seen from Python, per drone and step; the table also gives the
fallbacks and the smallest distance between any two drones over the run.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "tracking"))

from onboard.formation.mpc import FormationMPC, MpcConfig, SharedPlan  # noqa: E402
from onboard.formation.slots import assign_slot_angles  # noqa: E402
from onboard.tracking.filter import CooperativeFilter  # noqa: E402
from onboard.tracking.measurement import box_from_person, measurement_from_box  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe_machine  # noqa: E402


def machine() -> str:
    import casadi

    return describe_machine(f"numpy {np.__version__}", f"casadi {casadi.__version__}")

def pct(a, q):
    return float(np.percentile(np.asarray(a) * 1e3, q))


def _timed(fn, out_wall, out_cpu):
    t0, c0 = time.perf_counter(), time.process_time()
    fn()
    out_wall.append(time.perf_counter() - t0)
    out_cpu.append(time.process_time() - c0)


def bench_filter(n_meas: int = 1200) -> list[tuple[str, float, float, float, float]]:
    from tracking_scene import CAM, look_at_pose, simulate  # the tests' scene generator

    rng = np.random.default_rng(0)
    meas = simulate(n_meas / 12.0, rng)  # 3 drones x 4 Hz
    rows = []
    # the measurement with the feet-on-the-ground term (the agent's default) and with the height prior alone
    # measurement from a box
    p = np.array([8.0, 3.0, -0.85])
    T = look_at_pose(np.array([0.0, 0.0, -8.0]), p)
    box, _ = box_from_person(p, CAM, T)
    ts, cs = [], []
    for mode in ("height_and_ground", "height_prior"):
        ts, cs = [], []
        for _ in range(300):
            _timed(lambda: measurement_from_box(box, CAM, T, None, mode=mode), ts, cs)
        rows.append((f"measurement_from_box ({mode} + covariance)", pct(ts, 50), pct(ts, 99), max(ts) * 1e3, pct(cs, 50)))
    # one offset state per drone heard from: 6 + 3 N states
    for n in (3, 5, 8):
        mm = meas if n == 3 else simulate(n_meas / (4.0 * n), np.random.default_rng(n), n=n)
        f = CooperativeFilter("drone_0")
        ts, cs = [], []
        for m in mm:
            _timed(lambda: f.add(m), ts, cs)
        rows.append((f"filter add, in order ({n} drones, {len(f.state[0])} states)", pct(ts, 50), pct(ts, 99), max(ts) * 1e3, pct(cs, 50)))
    # teammates' detections 0-0.5 s late: each late one re-runs the filter from the buffer
    arrival = [m.t_ns + (0 if m.source_id == "drone_0" else int(rng.uniform(0, 0.5e9))) for m in meas]
    late = [meas[i] for i in np.argsort(arrival, kind="stable")]
    f = CooperativeFilter("drone_0")
    ts, cs = [], []
    for m in late:
        _timed(lambda: f.add(m), ts, cs)
    rows.append((f"filter add, 0-0.5 s late teammates ({f.stats.refiltered} re-filters)", pct(ts, 50), pct(ts, 99), max(ts) * 1e3, pct(cs, 50)))
    ts, cs = [], []
    for k in range(1000):
        _timed(lambda: f.estimate(meas[-1].t_ns + (k % 30) * 33_000_000), ts, cs)
    rows.append(("filter estimate (predict to now)", pct(ts, 50), pct(ts, 99), max(ts) * 1e3, pct(cs, 50)))
    return rows


def bench_mpc(n: int, solver: str, separation: str, steps: int) -> dict:
    cfg = MpcConfig(solver=solver, separation=separation, max_teammates=max(n - 1, 1), max_solve_time_s=1.0)
    ids = [f"drone_{k}" for k in range(n)]
    mpcs = {i: FormationMPC(i, cfg) for i in ids}
    # start in a line south of the person (crowded), converge to equally spaced slots around the walking person
    p = np.array([[-14.0, 4.0 * (k - (n - 1) / 2), -6.0] for k in range(n)])
    v = np.zeros((n, 3))
    angles = assign_slot_angles(ids, np.zeros(3), {i: p[k] for k, i in enumerate(ids)})
    # before the first plans arrive, teammates are known by their state (as the agent will do)
    plans = {i: SharedPlan.from_state(i, 0, p[k], v[k], cfg.dt_s, cfg.horizon_steps) for k, i in enumerate(ids)}
    times, totals, cpus = [], [], []
    fallbacks = 0
    dmin = np.inf
    for s in range(steps):
        t_ns = s * 100_000_000
        ts = s * 0.1
        person = np.array([0.8 * ts, 2.0 * math.sin(0.1 * ts), -0.85])
        person_v = np.array([0.8, 0.2 * math.cos(0.1 * ts), 0.0])
        res = {}
        for k, i in enumerate(ids):
            t0, c0 = time.perf_counter(), time.process_time()
            r = mpcs[i].step(t_ns, p[k], v[k], person, person_v, angles[i], {j: plans[j] for j in plans if j != i})
            totals.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
            res[i] = r
            times.append(r.solve_time_s)
        plans = {i: r.plan for i, r in res.items()}
        p = np.array([res[i].setpoint_position_ned_m for i in ids])
        v = np.array([res[i].setpoint_velocity_ned_m_s for i in ids])
        for a in range(n):
            for b in range(a + 1, n):
                dmin = min(dmin, float(np.linalg.norm(p[a] - p[b])))
    fallbacks = sum(m.fallback_count for m in mpcs.values())
    # how well the formation is held at the end: distance of each drone to its slot
    slot_err = np.mean([np.linalg.norm(res[i].reference_ned_m[0] - p[k]) for k, i in enumerate(ids)])
    return dict(
        n=n, solver=solver, sep=separation, med=pct(times, 50), p99=pct(times, 99), max=max(times) * 1e3,
        fallbacks=fallbacks, solves=len(times), dmin=dmin, slot_err=float(slot_err), step_med=pct(totals, 50), cpu_med=pct(cpus, 50), cpu_p99=pct(cpus, 99),
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=150, help="closed-loop MPC steps per configuration (0.1 s each)")
    ap.add_argument("--quick", action="store_true", help="OSQP only")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)  # fallbacks are counted in the table, not logged one by one
    print(f"machine: {machine()}")
    print()
    try:
        load = "load average %.2f %.2f %.2f" % os.getloadavg()
    except OSError:
        load = "load average unknown"
    print(f"{load} (wall-clock p99 on a shared machine mostly measures the other processes; CPU time does not)")
    print()
    print("| cooperative filter | median ms | p99 ms | max ms | CPU median ms |")
    print("| --- | --- | --- | --- | --- |")
    for name, med, p99, mx, cpu in bench_filter():
        print(f"| {name} | {med:.3f} | {p99:.3f} | {mx:.3f} | {cpu:.3f} |")
    print()
    configs = [(n, "osqp", "bvc") for n in (3, 5, 8)]
    if not a.quick:
        configs += [(3, "qpoases", "bvc"), (3, "ipopt", "bvc"), (3, "ipopt", "nonconvex"), (5, "ipopt", "nonconvex"), (8, "ipopt", "nonconvex")]
    print(f"formation MPC: horizon 15 x 0.1 s, 6 states / 3 inputs, {a.steps} closed-loop steps per drone, warm-started")
    print()
    print("| drones | solver | separation | median ms | p99 ms | max ms | solves | fallbacks | min distance m (>= 3) | slot error at end m | whole step() median ms | step() CPU median / p99 ms |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for n, solver, sep in configs:
        r = bench_mpc(n, solver, sep, a.steps)
        print(f"| {r['n']} | {r['solver']} | {r['sep']} | {r['med']:.2f} | {r['p99']:.2f} | {r['max']:.2f} | {r['solves']} | {r['fallbacks']} | {r['dmin']:.2f} | {r['slot_err']:.2f} | {r['step_med']:.2f} | {r['cpu_med']:.2f} / {r['cpu_p99']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
