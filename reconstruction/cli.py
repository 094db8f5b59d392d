"""Reconstruction subcommands: ``skycap reconstruct`` and the ``skycap eval ...`` harnesses.

Each method package contributes through optional hooks, so methods can be added without touching this file:

* ``reconstruction.<method>.cli.register_eval(eval_subparsers)`` adds ``skycap eval <method> ...``
* ``reconstruction.<method>.cli.reconstruct_flight(flight_dir, args) -> int`` runs ``skycap reconstruct
  FLIGHT_DIR --method <method>``; ``add_reconstruct_args(parser)`` may add its options.
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
    for m in methods:
        mod = _method_cli(m)
        if hasattr(mod, "add_reconstruct_args"):
            mod.add_reconstruct_args(rc)
    rc.set_defaults(func=_reconstruct)


def _reconstruct(args: argparse.Namespace) -> int:
    from skycap.errors import SkycapError

    method = args.method
    if method is None:
        n = len(list(Path(args.flight_dir).glob("drone_*.mcap")))
        method = "multiview" if n > 1 else "monocular"
    mod = _method_cli(method)
    if mod is None or not hasattr(mod, "reconstruct_flight"):
        raise SkycapError(f"reconstruction method {method!r} is not available in this build")
    return int(mod.reconstruct_flight(Path(args.flight_dir), args) or 0)
