"""Reconstruction subcommands: ``skycap process`` (alias ``skycap reconstruct``) and the ``skycap eval ...`` harnesses.

``skycap process FLIGHT_DIR`` is a thin layer over the library (:func:`reconstruction.process.process`): it parses
the arguments, builds the :class:`reconstruction.process.config.ProcessConfig` (``--config`` / ``--set`` and the
flags below), shows a progress bar driven by the :class:`reconstruction.process.events.ProgressEvent` s, prints the
summary and returns the exit code. ``skycap reconstruct`` is the same command under its former name.

Each method package contributes through optional hooks, so methods can be added without touching this file:

* ``reconstruction.<method>.cli.register_eval(eval_subparsers)`` adds ``skycap eval <method> ...``
* ``reconstruction.<method>.cli.add_reconstruct_args(parser)`` adds its ``skycap process`` options and
  ``reconstruction.<method>.cli.reconstruct_config(args) -> (config, out_dir | None)`` turns them into the method's
  config (the fields that differ from the method's defaults become ``ProcessConfig.<method>`` settings; out_dir
  None: the flight's folder for the method).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path

METHODS = ("multiview", "monocular")


def _method_cli(method: str):
    try:
        return importlib.import_module(f"reconstruction.{method}.cli")
    except ModuleNotFoundError as e:
        if e.name and f"reconstruction.{method}".startswith(e.name) or e.name == f"reconstruction.{method}.cli":
            return None
        raise


def register(sub: argparse._SubParsersAction) -> None:
    from skycap.config import add_config_args

    ev = sub.add_parser("eval", help="evaluate a reconstruction method on real motion capture")
    ev_sub = ev.add_subparsers(dest="eval_method", metavar="METHOD")
    methods = [m for m in METHODS if _method_cli(m) is not None]
    for m in methods:
        mod = _method_cli(m)
        if hasattr(mod, "register_eval"):
            mod.register_eval(ev_sub)
    ev.set_defaults(func=lambda a: ev.print_help() or 2)

    rc = sub.add_parser(
        "process", aliases=["reconstruct"],
        help="3D body motion of a recorded flight from its images (keypoint models -> fit -> BVH/NPZ/CSV/RRD)",
        description="Process a recorded flight: per drone the person's box in each frame, the keypoint models on the "
        "recorded images (fused), the multi-view fit (monocular with one drone) in overlapping windows, the exports. "
        "Each step is cached in FLIGHT_DIR/processing/ and resumes after a crash or Ctrl-C. `skycap reconstruct` is "
        "the same command. Example: skycap process flights/demo --keypoints sim --set windows.window_s=30")
    rc.add_argument("flight_dir", type=Path, help="flight folder written by the onboard recorder / demo")
    rc.add_argument("--method", choices=METHODS, default=None, help="default: multiview with >1 usable drone, else monocular")
    rc.add_argument("--sortie", type=int, default=None, metavar="N",
                    help="only sortie N of each drone (default: the whole flight, every sortie in order)")
    rc.add_argument("--keypoints", choices=("models", "sim"), default=None,
                    help="models (default): the keypoint models on the recorded images; sim: the simulator's recorded "
                         "noisy true keypoints (evaluation)")
    rc.add_argument("--models", default=None, help="comma-separated keypoint models (default movenet_lightning,blazepose_lite; movenet_lightning,blazepose_full: a few mm more accurate, 1.16x the time)")
    rc.add_argument("--threads", type=int, default=None, help="onnxruntime threads per keypoint model (default 1; keypoints.workers drones run at once, default 2)")
    rc.add_argument("--window-s", type=float, default=None, help="fit window length, s (default 60)")
    rc.add_argument("--out", type=Path, default=None, help="output folder (default: the method's folder of the flight)")
    rc.add_argument("--no-cache", action="store_true", help="neither read nor write FLIGHT_DIR/processing/")
    add_config_args(rc)
    from reconstruction.jobs.config import add_job_args

    add_job_args(rc)
    for m in methods:
        mod = _method_cli(m)
        if hasattr(mod, "add_reconstruct_args"):
            mod.add_reconstruct_args(rc)
    rc.set_defaults(func=_process)


def _changed(cfg, default, prefix: str) -> dict:
    """Dotted keys of ``cfg``'s fields that differ from ``default`` (nested dataclasses flattened)."""
    from skycap.config import config_to_dict

    out = {}

    def walk(a, b, p):
        for k, v in a.items():
            if isinstance(v, dict) and isinstance(b.get(k), dict):
                walk(v, b[k], f"{p}{k}.")
            elif v != b.get(k):
                out[f"{p}{k}"] = v

    walk(config_to_dict(cfg), config_to_dict(default), prefix)
    return out


class ProgressBar:
    """Draws :class:`ProgressEvent` s: a tqdm bar per step on a terminal (a plain ``\\r`` line where tqdm is not
    installed), one line per 10 % of a step otherwise (logs)."""

    def __init__(self, stream=None) -> None:
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        try:
            from tqdm import tqdm
        except ImportError:  # pragma: no cover - tqdm is a base dependency, but the bar must not need it
            tqdm = None
        self._tqdm = tqdm if self.tty else None
        self._bar = None
        self._step = None
        self._last = -1

    def __call__(self, ev) -> None:
        eta = "" if ev.eta_s is None else f" eta {ev.eta_s:.0f} s"
        if ev.step != self._step:
            self.close()
            self._step, self._last = ev.step, -1
            if self._tqdm is not None:
                self._bar = self._tqdm(total=100, desc=ev.step, leave=False, file=self.stream,
                                       bar_format="{desc:>9}: {percentage:3.0f}%|{bar}| {postfix}")
        pct = int(round(100 * ev.fraction))
        if self._bar is not None:
            self._bar.n = pct
            self._bar.set_postfix_str(f"{ev.message}{eta}", refresh=False)
            self._bar.refresh()
        elif self.tty:
            width = 30
            fill = int(width * ev.fraction)
            self.stream.write(f"\r{ev.step:>9}: {pct:3d}% [{'#' * fill}{'.' * (width - fill)}] {ev.message[:60]:60s}{eta}")
            self.stream.flush()
        elif pct // 10 != self._last // 10:
            self.stream.write(f"{time.strftime('%H:%M:%S')} {ev.step}: {pct}%{eta} {ev.message}\n")
            self.stream.flush()
        self._last = pct

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
        elif self.tty and self._step is not None:
            self.stream.write("\n")
        self._bar = None


def process_config(args: argparse.Namespace):
    """The :class:`ProcessConfig` of ``skycap process``'s arguments (``--config``/``--set``, then the flags)."""
    from flightdata.folder import FlightFolder
    from reconstruction.process.config import ProcessConfig
    from skycap.config import config_from_args

    extra = {"keypoints.source": args.keypoints, "keypoints.threads": args.threads, "windows.window_s": args.window_s,
             "method": args.method, "sortie": args.sortie, "out_dir": args.out, "cache": False if args.no_cache else None}
    if args.models:
        extra["keypoints.models"] = [m.strip() for m in args.models.split(",") if m.strip()]
    base = ProcessConfig()
    outs = {}
    for m in METHODS:
        mod = _method_cli(m)
        if mod is None or not hasattr(mod, "reconstruct_config"):
            continue
        mcfg, out = mod.reconstruct_config(args)
        extra.update(_changed(mcfg, getattr(base, m), f"{m}."))
        outs[m] = out
    if args.out is None and any(outs.values()):
        from reconstruction.api import choose_method

        method = args.method or choose_method(FlightFolder(args.flight_dir), args.sortie)
        extra["out_dir"] = outs.get(method)
    return config_from_args(ProcessConfig, args, extra).validate()


def _process(args: argparse.Namespace) -> int:
    import json

    from reconstruction.process.pipeline import process

    cfg = process_config(args)
    bar = ProgressBar()
    try:
        if getattr(args, "ray", None):
            # on a Ray cluster: the same pipeline as a job (reconstruction.jobs), its events drive the same bar
            from reconstruction.jobs import jobs_config_from_args, runner_from_config

            with runner_from_config(jobs_config_from_args(args)) as runner:
                job = runner.submit(args.flight_dir, cfg, processor="process")
                unsubscribe = job.subscribe(bar)
                try:
                    result = job.result()
                except KeyboardInterrupt:
                    job.cancel()
                    raise
                finally:
                    unsubscribe()
        else:
            result = process(args.flight_dir, cfg, progress=bar)
    finally:
        bar.close()
    print(json.dumps(result.summary, indent=2))
    return 0
