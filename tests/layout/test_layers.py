"""The package structure: import-linter's layer and no-cycle contracts, and a drone's base install."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from tests.helpers.paths import REPO


HEAVY = ("torch", "PySide6", "anny", "rerun", "pymavlink")

# Runs a skycap command with the extras' packages made unimportable, as on a drone's base install.
_BLOCKED_RUN = """
import importlib.abc, sys
BLOCKED = {blocked!r}
class _Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {{name!r}} (blocked: base install)", name=name)
        return None
sys.meta_path.insert(0, _Block())
from apps.cli import main
code = main({argv!r})
leaked = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
assert not leaked, leaked
sys.exit(code)
"""


def test_import_linter_contracts_hold():
    exe = Path(sys.executable).with_name("lint-imports")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "importlinter.cli"]
    r = subprocess.run([*cmd, "--no-cache"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]
    assert "2 kept, 0 broken" in r.stdout


def test_base_dependencies_carry_no_extras():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    base = " ".join(project["dependencies"]).lower()
    for name in ("torch", "pyside6", "anny", "rerun", "pymavlink"):
        assert name not in base, f"{name} is a base dependency; a drone's install must not pull it"
    extras = project["optional-dependencies"]
    assert {"sim", "recon", "gcs", "all", "test"} <= set(extras)
    assert "import-linter" in " ".join(extras["test"])


def _run_blocked(argv: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    code = _BLOCKED_RUN.format(blocked=set(HEAVY), argv=argv)
    return subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                          env={**__import__("os").environ, "PYTHONPATH": str(REPO)})


def test_agent_help_and_log_info_without_the_extras(tmp_path):
    r = _run_blocked(["agent", "--help"], tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "--record-dir" in r.stdout

    from flightdata.recorder import Recorder
    from shared_msgs import Health

    with Recorder.new_sortie(tmp_path, "drone_1") as rec:
        rec.record_message("health", Health(header=Health.make_header("drone_1", 1), role="agent", state="idle"))
    [log] = tmp_path.glob("drone_1.s001.mcap")
    r = _run_blocked(["log", "info", str(log)], tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "health" in r.stdout and "finalised" in r.stdout


def test_a_command_that_needs_an_extra_says_which(tmp_path):
    r = _run_blocked(["reconstruct", str(tmp_path)], tmp_path)
    assert r.returncode == 2, (r.returncode, r.stderr[-3000:])
    assert "pip install" in r.stderr and "recon" in r.stderr, r.stderr[-2000:]


@pytest.mark.parametrize("pkg", ["onboard", "flightdata", "comms"])
def test_drone_packages_import_nothing_heavy(pkg):
    code = (f"import sys, pkgutil, importlib, {pkg}\n"
            f"for m in pkgutil.walk_packages({pkg}.__path__, '{pkg}.'):\n"
            f"    importlib.import_module(m.name)\n"
            f"bad = sorted({{m.split('.')[0] for m in sys.modules}} & {set(HEAVY)!r})\n"
            f"assert not bad, bad\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
