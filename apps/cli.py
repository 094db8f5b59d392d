"""The one command-line tool: ``skycap <subcommand> ...``.

Each part of the system registers its own subcommands in a ``cli.py`` module exposing
``register(subparsers)``; heavy imports happen inside the command functions so that
``skycap --help`` stays fast. A registered command sets ``func`` (taking the parsed args, returning an
exit code) with ``parser.set_defaults(func=...)``.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from skycap import __version__
from skycap.errors import SkycapError
from skycap.logsetup import setup_logging

#: Modules that contribute subcommands, in help order.
COMMAND_MODULES = (
    "apps.demo",
    "apps.faults",
    "simulator.cli",
    "simulator.scene.cli",
    "onboard.cli",
    "onboard.camera_cli",
    "flightdata.cli",
    "onboard.detector.cli",
    "groundstation.cli",
    "comms.cli",
    "reconstruction.cli",
    "reconstruction.keypoints.cli",
    "evaluation.cli",
    "apps.refine",
)

#: The subcommands each module registers. ``skycap <command> ...`` imports only that command's module (a
#: drone's ``skycap agent``, restarted after a crash, does not import the simulator, the reconstruction and the
#: evaluation first: ~2 s of a 3 s start on a loaded 2-core machine); ``skycap --help`` imports them all.
#: tests/skycap/test_cli_commands.py checks this table against what the modules register.
COMMANDS_OF_MODULE = {
    "apps.demo": ("demo",),
    "apps.faults": ("faults",),
    "simulator.cli": ("sim",),
    "simulator.scene.cli": ("sim-camera", "sim-preview"),
    "onboard.cli": ("agent",),
    "onboard.camera_cli": ("camera",),
    "flightdata.cli": ("log",),
    "onboard.detector.cli": ("detect",),
    "groundstation.cli": ("fleet", "gs"),
    "comms.cli": ("keys",),
    "reconstruction.cli": ("eval", "process", "reconstruct"),
    "reconstruction.keypoints.cli": ("keypoints",),
    "evaluation.cli": ("harness",),
    "apps.refine": ("refine",),
}

log = logging.getLogger("skycap")

#: Packages of the optional extras (pyproject.toml) -> the extra that installs them. A drone's base install
#: lacks them; a command that needs one says which extra to install.
EXTRA_OF_PACKAGE = {"torch": "recon", "anny": "recon", "rerun": "recon", "PySide6": "gcs", "pymavlink": "sim"}


def missing_extra(e: ModuleNotFoundError) -> str | None:
    """The extra whose package ``e`` found missing, or None when it is not one of the extras' packages."""
    return EXTRA_OF_PACKAGE.get((e.name or "").split(".")[0])


def _command_module(argv: list[str]) -> str | None:
    """The module of the command ``argv`` names (its first word that is not an option), if the table knows it."""
    words = [a for a in argv if not a.startswith("-")]
    if not words or "--log-level" in argv:  # --log-level takes a value: leave such a line to the full parser
        return None
    return next((m for m, cmds in COMMANDS_OF_MODULE.items() if words[0] in cmds and m in COMMAND_MODULES), None)


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command module's subcommands (``only``: of that module alone)."""
    parser = argparse.ArgumentParser(prog="skycap", description="skycap: markerless human motion capture from a fleet of autonomous camera drones.")
    parser.add_argument("--version", action="version", version=f"skycap {__version__}")
    parser.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING or ERROR (default INFO)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in (COMMAND_MODULES if only is None else (only,)):
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as e:  # a part that is not built yet
            if e.name and name.startswith(e.name):
                continue
            raise
        register = getattr(mod, "register", None)
        if register is not None:
            register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser(only=_command_module(sys.argv[1:] if argv is None else argv))
    args = parser.parse_args(argv)
    setup_logging(args.log_level)
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 2
    try:
        return int(func(args) or 0)
    except KeyboardInterrupt:
        log.warning("interrupted")
        return 130
    except ModuleNotFoundError as e:
        extra = missing_extra(e)
        if extra is None:
            raise
        log.debug("details", exc_info=True)
        print(f"skycap {args.command}: error: this command needs {e.name!r}, which the base install (a drone's) "
              f"leaves out; install the '{extra}' extra: pip install 'skycap[{extra}]' (or 'skycap[all]')",
              file=sys.stderr)
        return 2
    except Exception as e:  # clear one-line error for expected problems; traceback at DEBUG
        if isinstance(e, SkycapError):
            log.debug("details", exc_info=True)
            print(f"skycap {args.command}: error: {e}", file=sys.stderr)
            return 2
        raise


if __name__ == "__main__":
    sys.exit(main())
