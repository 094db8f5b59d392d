"""Seconds of processing per second of flight, per step, with 1 and 2 local workers and with Ray on this machine.

    python bench/bench_process.py FLIGHT_DIR [--processor reconstruct | package.module:function]
                                  [--config-factory package.module:function] [--copies 2]
                                  [--modes local1,local2,ray] [--ray ADDRESS] [--keep DIR]

The processor runs through the job API (:mod:`reconstruction.jobs`) on ``--copies`` fresh copies of the flight
(the folder's top-level files only: recordings, plan, truth, configs -- no outputs, no caches, so nothing is
resumed) in each mode:

* ``local1``: a LocalRunner with 1 worker process (the copies one after the other);
* ``local2``: a LocalRunner with 2 worker processes (two flights at once);
* ``ray``: a RayRunner on a Ray cluster started here (``ray.init(address="local")``, this machine's CPUs) or on
  ``--ray ADDRESS``; Ray's start-up is reported apart.

Each worker / Ray task gets ``--threads`` BLAS / torch threads (default 1, as Ray gives a 1-CPU task). Flight
seconds: the span of the drones' recordings (MCAP message times, first to last). Per step: the time from a step's
first progress event to the next step's (the last to the job's end), averaged over the copies, divided by the
flight seconds. ``wall``: submit of the first copy to the end of the last, per second of flight of all copies (the
throughput); ``latency``: one job's submit to its end per second of its flight (mean). ``queued+start``: submit to
the processor running (waiting for a free worker, then the worker process's start-up, or Ray's scheduling), mean.

The processor's config: ``--config-factory module:function`` (called with no argument), else None (the
processor's defaults; for ``reconstruct``, :class:`reconstruction.jobs.adapters.ReconstructJobConfig()`).
"""

from __future__ import annotations

import argparse
import importlib
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._machine import describe_machine  # noqa: E402


def flight_seconds(flight: Path) -> float:
    """The span of the drones' recordings (MCAP statistics: first to last message time)."""
    from mcap.reader import make_reader

    from flightdata.folder import FlightFolder

    t0, t1 = None, None
    for sorties in FlightFolder(flight).drone_logs().values():
        for s in sorties:
            with open(s.path, "rb") as f:
                st = make_reader(f).get_summary().statistics
            t0 = st.message_start_time if t0 is None else min(t0, st.message_start_time)
            t1 = st.message_end_time if t1 is None else max(t1, st.message_end_time)
    if t0 is None:
        raise SystemExit(f"{flight} holds no drone recording")
    return (t1 - t0) / 1e9


def fresh_copy(flight: Path, dest: Path) -> Path:
    dest.mkdir(parents=True)
    for p in flight.iterdir():
        if p.is_file():
            shutil.copy2(p, dest / p.name)
    return dest


def step_seconds(job) -> dict[str, float]:
    """Per step: first event of the step to the first of the next (the last step to the job's end)."""
    firsts: list[tuple[str, float]] = []
    for ev in job.events:
        if not firsts or firsts[-1][0] != ev.step:
            if ev.step not in dict(firsts):
                firsts.append((ev.step, ev.elapsed_s))
    out = {}
    for i, (step, t) in enumerate(firsts):
        end = firsts[i + 1][1] if i + 1 < len(firsts) else job.elapsed_s
        out[step] = max(0.0, end - t)
    return out


def run_mode(name: str, runner, flight: Path, copies: int, processor: str, cfg, work: Path, flight_s: float) -> dict:
    dirs = [fresh_copy(flight, work / f"{name}-{i}") for i in range(copies)]
    t0 = time.monotonic()
    jobs = [runner.submit(d, cfg, processor=processor) for d in dirs]
    for j in jobs:
        j.result()  # raises the job's error
    wall = time.monotonic() - t0
    steps: dict[str, float] = {}
    for j in jobs:
        for s, v in step_seconds(j).items():
            steps[s] = steps.get(s, 0.0) + v / copies
    latency = sum(j.finished_at - j.submitted_at for j in jobs) / copies
    start = sum(j.started_at - j.submitted_at for j in jobs) / copies
    return {"mode": name, "wall_s": wall, "wall_per_flight_s": wall / (copies * flight_s),
            "latency_per_flight_s": latency / flight_s, "start_s": start,
            "steps_per_flight_s": {s: v / flight_s for s, v in steps.items()}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("flight_dir", type=Path)
    ap.add_argument("--processor", default="reconstruct", help="registered name or import path module:function")
    ap.add_argument("--config-factory", default=None, metavar="MODULE:FUNCTION")
    ap.add_argument("--copies", type=int, default=2)
    ap.add_argument("--modes", default="local1,local2,ray")
    ap.add_argument("--ray", default="local", metavar="ADDRESS", help="Ray cluster (default: start one here)")
    ap.add_argument("--threads", type=int, default=1, help="BLAS / torch threads per local worker")
    ap.add_argument("--keep", type=Path, default=None, help="keep the processed copies under this folder")
    a = ap.parse_args()

    from reconstruction.jobs import LocalRunner
    from reconstruction.jobs.registry import processor_spec

    flight = a.flight_dir.resolve()
    fs = flight_seconds(flight)
    processor = processor_spec(a.processor)
    cfg = None
    if a.config_factory:
        mod, _, fn = a.config_factory.partition(":")
        cfg = getattr(importlib.import_module(mod), fn)()
    work = Path(tempfile.mkdtemp(prefix="bench-process-", dir=a.keep)) if a.keep else Path(tempfile.mkdtemp(prefix="bench-process-"))
    rows, ray_start = [], None
    try:
        for mode in a.modes.split(","):
            print(f"... {mode}", file=sys.stderr, flush=True)
            if mode in ("local1", "local2"):
                with LocalRunner(int(mode[-1]), threads_per_worker=a.threads) as runner:
                    rows.append(run_mode(mode, runner, flight, a.copies, processor, cfg, work, fs))
            elif mode == "ray":
                from reconstruction.jobs.ray_runner import RayRunner

                t0 = time.monotonic()
                kw = dict(include_dashboard=False, _node_ip_address="127.0.0.1") if a.ray == "local" else {}
                with RayRunner(a.ray, **kw) as runner:
                    ray_start = time.monotonic() - t0
                    rows.append(run_mode(mode, runner, flight, a.copies, processor, cfg, work, fs))
            else:
                raise SystemExit(f"unknown mode {mode!r}: use local1, local2, ray")
    finally:
        if not a.keep:
            shutil.rmtree(work, ignore_errors=True)

    steps = list(dict.fromkeys(s for r in rows for s in r["steps_per_flight_s"]))
    print(f"processing {processor} of {flight.name}: {fs:.1f} s of flight, {a.copies} copies per mode, "
          f"{a.threads} thread(s) per worker" + (f"; Ray start-up {ray_start:.1f} s (not counted)" if ray_start else ""))
    head = ["mode", "wall s", "wall/flight-s", "latency/flight-s", "queued+start s"] + [f"{s}/flight-s" for s in steps]
    print(" | ".join(head))
    print(" | ".join("---" for _ in head))
    for r in rows:
        print(" | ".join([r["mode"], f"{r['wall_s']:.1f}", f"{r['wall_per_flight_s']:.2f}",
                          f"{r['latency_per_flight_s']:.2f}", f"{r['start_s']:.1f}"]
                         + [f"{r['steps_per_flight_s'].get(s, 0.0):.3f}" for s in steps]))
    print(f"machine: {describe_machine()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
