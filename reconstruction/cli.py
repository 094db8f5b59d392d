"""Reconstruction subcommands: ``skycap reconstruct`` and the ``skycap eval ...`` harnesses.

``skycap reconstruct`` is a thin layer over the library (:func:`reconstruction.api.reconstruct_flight`): it parses
the arguments, builds the method's config, calls the library, prints the summary and returns the exit code.

Each method package contributes through optional hooks, so methods can be added without touching this file:

* ``reconstruction.<method>.cli.register_eval(eval_subparsers)`` adds ``skycap eval <method> ...``
* ``reconstruction.<method>.cli.add_reconstruct_args(parser)`` adds its ``skycap reconstruct`` options and
  ``reconstruction.<method>.cli.reconstruct_config(args) -> (config, out_dir | None)`` turns them into the method's
  config for :func:`reconstruction.api.reconstruct_flight` (out_dir None: the flight's folder for the method).
"""

from __future__ import annotations

import argparse
import importlib
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
    ev = sub.add_parser("eval", help="evaluate a reconstruction method on real motion capture")
    ev_sub = ev.add_subparsers(dest="eval_method", metavar="METHOD")
    methods = [m for m in METHODS if _method_cli(m) is not None]
    for m in methods:
        mod = _method_cli(m)
        if hasattr(mod, "register_eval"):
            mod.register_eval(ev_sub)
    ev.set_defaults(func=lambda a: ev.print_help() or 2)

    rc = sub.add_parser("reconstruct", help="reconstruct the 3D body motion of a recorded flight")
    rc.add_argument("flight_dir", type=Path, help="flight folder written by the onboard recorder / demo")
    rc.add_argument("--method", choices=METHODS, default=None, help="default: multiview with >1 drone, else monocular")
    rc.add_argument("--sortie", type=int, default=None, metavar="N",
                    help="reconstruct only sortie N of each drone (default: the whole flight, every sortie in order)")
    for m in methods:
        mod = _method_cli(m)
        if hasattr(mod, "add_reconstruct_args"):
            mod.add_reconstruct_args(rc)
    rc.set_defaults(func=_reconstruct)


class _ProgressBars:
    """``progress(stage, done, total)`` for the terminal: one transient bar per stage on stderr (as the fit's own
    bars were), nothing when stderr is not a terminal."""

    def __init__(self) -> None:
        self._bar = None
        self._stage = None

    def __call__(self, stage: str, done: int, total: int) -> None:
        import sys

        if not sys.stderr.isatty():
            return
        from tqdm import tqdm

        if stage != self._stage:
            self.close()
            self._stage = stage
            self._bar = tqdm(total=total, desc=stage, leave=False)
        self._bar.total = total
        self._bar.n = done
        self._bar.refresh()
        if done >= total:
            self.close()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
        self._bar, self._stage = None, None


def _reconstruct(args: argparse.Namespace) -> int:
    import json

    from flightdata.folder import FlightFolder
    from reconstruction.api import choose_method, reconstruct_flight
    from skycap.errors import SkycapError

    flight = FlightFolder(args.flight_dir)
    method = args.method or choose_method(flight, args.sortie)
    mod = _method_cli(method)
    if mod is None or not hasattr(mod, "reconstruct_config"):
        raise SkycapError(f"reconstruction method {method!r} is not available in this build")
    config, out_dir = mod.reconstruct_config(args)
    bars = _ProgressBars()
    try:
        result = reconstruct_flight(flight, method, config, sortie=args.sortie, out_dir=out_dir, progress=bars)
    finally:
        bars.close()
    print(json.dumps(result.summary, indent=2))
    return 0
