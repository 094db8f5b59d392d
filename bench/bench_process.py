"""Seconds of processing per second of flight, per step: ``skycap process`` in this process, with 1 and 2 local workers
and with Ray on this machine.

    python bench/bench_process.py FLIGHT_DIR [--modes direct,local1,local2,ray] [--copies 2] [--set KEY=VALUE ...]
                                  [--processor process_summary | reconstruct | package.module:function]
                                  [--config-factory package.module:function] [--ray ADDRESS] [--keep DIR]

    skycap demo --drones 3 --duration 20 --set reconstruct=false --out /tmp/flight     # 3 drones, 10 Hz images
    python bench/bench_process.py /tmp/flight --modes direct --copies 1                 # the CLI's path, once
    python bench/bench_process.py /tmp/flight --modes direct --copies 1 --set keypoints.workers=1 \
        --set keypoints.threads=2 --set keypoints.track_rois=false                      # the former defaults

The processor (default ``process_summary``: :func:`reconstruction.process.process` with a plain-data result; its
config is the ``--set`` overrides of :class:`reconstruction.process.ProcessConfig`, after ``export.extra=[]`` and
``export.rrd=false`` -- the processing, not the optional viewers' files) runs on ``--copies`` fresh copies of the
flight (the folder's top-level files only: recordings, plan, truth, configs -- no outputs, no caches, so nothing is
resumed) in each mode:

* ``direct``: :func:`reconstruction.process.process` called here, one copy after the other (``skycap process``);
* ``local1``: a LocalRunner with 1 worker process (the copies one after the other);
* ``local2``: a LocalRunner with 2 worker processes (two flights at once);
* ``ray``: a RayRunner on a Ray cluster started here (``ray.init(address="local")``, this machine's CPUs) or on
  ``--ray ADDRESS``; Ray's start-up is reported apart.

Each worker / Ray task gets ``--threads`` BLAS / torch threads (default 1, as Ray gives a 1-CPU task). Flight
seconds: the span of the recorded camera frames (the processed summary's ``flight_images_span_s``, what
``reconstruction.seconds_per_flight_second`` divides by); for a processor without that summary, the span of the
drones' recordings (MCAP message times, first to last). Per step: the summary's step seconds (else the time from a
step's first progress event to the next step's), averaged over the copies, divided by the flight seconds. ``wall``:
start of the first copy to the end of the last, per second of flight of all copies (the throughput; ``<= 1``: as
fast as the flight was flown); ``latency``: one job's submit to its end per second of its flight (mean).
``queued+start``: submit to the processor running (waiting for a free worker, then the worker process's start-up,
or Ray's scheduling), mean. With the simulator's ``truth.mcap`` in the flight, the first copy's motion is scored
(:func:`evaluation.flight.reconstruction_accuracy`: MPJPE / PA-MPJPE / W-MPJPE over the whole motion, mm). The load
average is printed before and after each mode (the machine is often shared: compare modes and configs run
back to back, not figures from different times).

``--config-factory module:function`` (called with no argument) gives the processor's config instead of ``--set``.
"""

from __future__ import annotations

import argparse
import importlib
import os
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
    """Per step: the processed summary's step seconds when the result carries them, else first event of the step to
    the first of the next (the last step to the job's end)."""
    res = job.result()
    summary = res.get("summary") if isinstance(res, dict) else getattr(res, "summary", None)
    if isinstance(summary, dict) and isinstance(summary.get("steps"), dict):
        return {k: float(v.get("seconds", 0.0)) for k, v in summary["steps"].items()}
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


def _summary(res) -> dict:
    s = res.get("summary") if isinstance(res, dict) else getattr(res, "summary", None)
    return s if isinstance(s, dict) else {}


def accuracy(copy: Path, res) -> dict:
    """MPJPE / PA-MPJPE / W-MPJPE (mm, whole motion) of a processed copy against its truth.mcap; {} without one."""
    from evaluation.flight import reconstruction_accuracy

    npz = (_summary(res).get("outputs") or {}).get("npz")
    if not npz or not (copy / "truth.mcap").is_file():
        return {}
    acc = reconstruction_accuracy(copy, motion_npz=npz)
    return {k: acc[k] for k in ("mpjpe_mm", "pa_mpjpe_mm", "w_mpjpe_mm") if k in acc}


class _DirectJob:
    """What run_mode reads of a job, for a flight processed in this process."""

    def __init__(self, processor, flight: Path, cfg):
        self.events, self.submitted_at = [], time.monotonic()
        self.started_at = self.submitted_at
        self._res = processor(flight, cfg, progress=self._event, cancel=None)
        self.finished_at = time.monotonic()
        self.elapsed_s = self.finished_at - self.started_at

    def _event(self, ev) -> None:
        from types import SimpleNamespace

        self.events.append(SimpleNamespace(step=ev.step, elapsed_s=time.monotonic() - self.started_at))

    def result(self):
        return self._res


class DirectRunner:
    """The processor called in this process (the ``skycap process`` path): each submit runs to its end."""

    def __init__(self, processor: str):
        from reconstruction.jobs.registry import resolve_processor

        self.processor = resolve_processor(processor)

    def submit(self, flight: Path, cfg, processor=None) -> _DirectJob:
        return _DirectJob(self.processor, flight, cfg)


def run_mode(name: str, runner, flight: Path, copies: int, processor: str, cfg, work: Path, fallback_s: float) -> dict:
    dirs = [fresh_copy(flight, work / f"{name}-{i}") for i in range(copies)]
    load0 = os.getloadavg()[0]
    t0 = time.monotonic()
    jobs = [runner.submit(d, cfg, processor=processor) for d in dirs]
    for j in jobs:
        j.result()  # raises the job's error
    wall = time.monotonic() - t0
    flight_s = [float(_summary(j.result()).get("flight_images_span_s") or fallback_s) for j in jobs]
    steps: dict[str, float] = {}
    for j, fs in zip(jobs, flight_s):
        for s, v in step_seconds(j).items():
            steps[s] = steps.get(s, 0.0) + v / fs / copies
    latency = sum((j.finished_at - j.submitted_at) / fs for j, fs in zip(jobs, flight_s)) / copies
    start = sum(j.started_at - j.submitted_at for j in jobs) / copies
    frames = sum(int((_summary(j.result()).get("stats") or {}).get("frames_computed", 0)) for j in jobs) / copies
    return {"mode": name, "wall_s": wall, "wall_per_flight_s": wall / sum(flight_s), "flight_s": flight_s[0],
            "latency_per_flight_s": latency, "start_s": start, "steps_per_flight_s": steps, "frames": frames,
            "accuracy": accuracy(dirs[0], jobs[0].result()), "load": (load0, os.getloadavg()[0])}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("flight_dir", type=Path)
    ap.add_argument("--processor", default="process_summary", help="registered name or import path module:function")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="ProcessConfig override (process processors), repeatable")
    ap.add_argument("--config-factory", default=None, metavar="MODULE:FUNCTION")
    ap.add_argument("--copies", type=int, default=2)
    ap.add_argument("--modes", default="direct,local1,local2,ray")
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
    elif "process" in processor:
        cfg = ["export.extra=[]", "export.rrd=false", *a.sets]
    work = Path(tempfile.mkdtemp(prefix="bench-process-", dir=a.keep)) if a.keep else Path(tempfile.mkdtemp(prefix="bench-process-"))
    rows, ray_start = [], None
    try:
        for mode in a.modes.split(","):
            print(f"... {mode} (load avg {os.getloadavg()[0]:.1f})", file=sys.stderr, flush=True)
            if mode == "direct":
                rows.append(run_mode(mode, DirectRunner(processor), flight, a.copies, processor, cfg, work, fs))
            elif mode in ("local1", "local2"):
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
                raise SystemExit(f"unknown mode {mode!r}: use direct, local1, local2, ray")
    finally:
        if not a.keep:
            shutil.rmtree(work, ignore_errors=True)

    steps = list(dict.fromkeys(s for r in rows for s in r["steps_per_flight_s"]))
    print(f"processing {processor} of {flight.name}: {rows[0]['flight_s'] if rows else fs:.1f} s of flight (camera "
          f"frames), {a.copies} copies per mode, {a.threads} thread(s) per worker"
          + (f", config overrides {cfg}" if isinstance(cfg, list) else "")
          + (f"; Ray start-up {ray_start:.1f} s (not counted)" if ray_start else ""))
    head = (["mode", "load avg (before/after)", "wall s", "wall/flight-s", "latency/flight-s", "queued+start s"]
            + [f"{s}/flight-s" for s in steps] + ["keypoint frames", "MPJPE / PA / W-MPJPE mm"])
    print(" | ".join(head))
    print(" | ".join("---" for _ in head))
    for r in rows:
        acc = r["accuracy"]
        print(" | ".join([r["mode"], f"{r['load'][0]:.1f} / {r['load'][1]:.1f}", f"{r['wall_s']:.1f}",
                          f"{r['wall_per_flight_s']:.2f}", f"{r['latency_per_flight_s']:.2f}", f"{r['start_s']:.1f}"]
                         + [f"{r['steps_per_flight_s'].get(s, 0.0):.3f}" for s in steps]
                         + [f"{r['frames']:.0f}", " / ".join(f"{acc[k]:.1f}" for k in ("mpjpe_mm", "pa_mpjpe_mm",
                                                                                       "w_mpjpe_mm") if k in acc) or "-"]))
    print(f"machine: {describe_machine()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
