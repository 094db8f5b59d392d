"""``skycap gs``'s configuration errors: each names the problem and the fix (exit 2), before any window opens."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

pytest.importorskip("PySide6")


def _gs(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    return subprocess.run([sys.executable, "-m", "apps.cli", "gs", *args], capture_output=True, text=True, timeout=60,
                          env=env)


def test_unknown_config_key_is_refused():
    r = _gs("--set", "ui.table_rate=5")
    assert r.returncode == 2 and "table_rate" in r.stderr, r.stderr


def test_tls_without_fleet_folder_names_the_fix():
    r = _gs("--set", "network.endpoint=\"tls/127.0.0.1:7999\"")
    assert r.returncode == 2 and "network.keys_dir is empty" in r.stderr and "skycap keys" in r.stderr, r.stderr


def test_fleet_folder_of_another_fleet_names_the_fix(tmp_path):
    from comms.security import FleetKeys

    fk = FleetKeys.create(tmp_path / "fleet", "alpha", drones=["drone_1"], days=1)
    r = _gs("--set", f"network.keys_dir=\"{fk.folder}\"", "--set", "fleet=\"bravo\"")
    assert r.returncode == 2 and "fleet folder of 'alpha'" in r.stderr and 'fleet="alpha"' in r.stderr, r.stderr
