"""apps.cli's table of the commands each module registers matches the registrations (a named command imports
only its module, so the table must not rot)."""

from __future__ import annotations

import argparse
import importlib
import subprocess
import sys

from apps.cli import COMMAND_MODULES, COMMANDS_OF_MODULE, _command_module


def test_the_table_names_what_each_module_registers():
    assert set(COMMANDS_OF_MODULE) == set(COMMAND_MODULES)
    for name in COMMAND_MODULES:
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError:
            continue  # an optional part not installed
        p = argparse.ArgumentParser()
        sub = p.add_subparsers()
        mod.register(sub)
        assert tuple(sub.choices) == COMMANDS_OF_MODULE[name], name


def test_a_named_command_imports_only_its_module():
    assert _command_module(["agent", "--drone-id", "drone_1"]) == "onboard.cli"
    assert _command_module(["--help"]) is None and _command_module([]) is None
    code = ("import sys; from apps.cli import build_parser, _command_module; "
            "build_parser(only=_command_module(['agent'])); "
            "print(sorted(m for m in ('apps.demo', 'evaluation.flight', 'simulator.cli') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr
