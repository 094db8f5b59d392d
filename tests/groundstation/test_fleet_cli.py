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
    # a plan the drones would refuse is not sent: the client names the field (exit 2, nothing published)
    r = _fleet(fl, "plan", "--drones", "drone_1", "--radius", "-1")
    assert r.returncode == 2 and "not sent: bad field radius_m=-1.0" in r.stderr, r.stdout + r.stderr
    r = _fleet(fl, "plan", "--drones", "drone_1,drone_1", "--radius", "5", "--altitude", "4")
    assert r.returncode == 2 and "drone_1 named more than once" in r.stderr, r.stdout + r.stderr
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


def test_fleet_cli_command_that_reaches_no_drone_is_an_error(flight):
    """No agent runs: a command for the whole fleet reaches nobody and says so (exit 2); one for a named drone
    that does not answer prints "no answer" (exit 1). Never a silent success."""
    fl = flight(1)
    r = _fleet(fl, "cmd", "land", "--wait", "1")
    assert r.returncode == 2 and "'land' not sent: no drone of fleet" in r.stderr, r.stdout + r.stderr
    r = _fleet(fl, "cmd", "land", "--target", "drone_1", "--wait", "1")
    assert r.returncode == 1 and "drone_1: no answer" in r.stdout, r.stdout + r.stderr
