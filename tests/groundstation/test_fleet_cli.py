"""``skycap fleet plan|cmd|watch`` against a running agent process (real Zenoh, real simulator)."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow


def _fleet(fl, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "apps.cli", "fleet", "--fleet", fl.fleet_id, "--zenoh-connect", fl.endpoint, *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60)


def test_fleet_cli_plan_cmd_watch(flight):
    fl = flight(1)
    fl.start_agent(0)
    assert fl.fleet.wait_until(lambda f: "drone_1" in f.states and f.states["drone_1"].health_ok, 40), fl.log("drone_1")
    r = _fleet(fl, "plan", "--drones", "drone_1", "--radius", "-1")
    assert r.returncode == 1 and "drone_1: refused - bad field radius_m=-1.0" in r.stdout, r.stdout + r.stderr
    r = _fleet(fl, "plan", "--drones", "drone_1", "--radius", "5", "--altitude", "4")
    assert r.returncode == 0 and "drone_1: accepted" in r.stdout, r.stdout + r.stderr
    r = _fleet(fl, "cmd", "pause", "--target", "drone_1")
    assert r.returncode == 1 and "drone_1: refused - nothing to pause in state idle" in r.stdout, r.stdout + r.stderr
    r = _fleet(fl, "cmd", "arm")
    assert r.returncode == 0 and "drone_1: accepted" in r.stdout, r.stdout + r.stderr
    r = _fleet(fl, "watch", "--duration", "1.5")
    assert r.returncode == 0
    row = next(line for line in r.stdout.splitlines() if line.startswith("drone_1"))
    assert "armed" in row and "True" in row, r.stdout
