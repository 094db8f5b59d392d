"""The deployment files: the example config loads and validates, the systemd unit runs the agent with it."""

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from onboard.config import AgentConfig
from skycap.config import load_config
from tests.helpers.paths import REPO

DEPLOY = REPO / "deploy"


def test_example_config_loads_and_validates():
    cfg = load_config(AgentConfig, DEPLOY / "agent.example.toml").validate()
    assert cfg.drone_id == "drone_1" and cfg.connection.startswith("serial://")
    assert cfg.safety.sigterm_action == "land"
    # deployed secure: every link mutual TLS with the fleet folder's certificates
    assert cfg.transport.security.keys_dir == "/etc/skycap/fleet"
    assert all(ep.startswith("tls/") for ep in cfg.transport.listen + cfg.transport.connect)
    cfg.transport.validate()


def test_systemd_unit_runs_the_agent_and_leaves_time_to_land():
    unit = (DEPLOY / "skycap-agent.service").read_text()
    assert "ExecStart=/opt/skycap/.venv/bin/skycap agent --config /etc/skycap/agent.toml" in unit
    timeout = int(next(l for l in unit.splitlines() if l.startswith("TimeoutStopSec=")).split("=")[1])
    assert timeout > AgentConfig().safety.sigterm_land_timeout_s


# --- the systemd units ------------------------------------------------------------------------------------
SYSTEMD_ANALYZE = shutil.which("systemd-analyze")
UNITS = ("skycap-agent.service", "skycap-camera.service")
needs_systemd_analyze = pytest.mark.skipif(SYSTEMD_ANALYZE is None,
                                           reason="systemd-analyze not installed (Debian/Ubuntu: apt install systemd)")


def _installable_copies(tmp_path: Path) -> list[Path]:
    """The units with ExecStart naming this machine's interpreter: ``systemd-analyze verify`` refuses a unit whose
    command does not exist, and /opt/skycap (the drone's install) does not exist on a build machine. The rest of
    each unit is verified as shipped."""
    out = []
    for name in UNITS:
        text = (DEPLOY / name).read_text()
        assert "ExecStart=/opt/skycap/.venv/bin/skycap " in text
        copy = tmp_path / name
        copy.write_text(text.replace("ExecStart=/opt/skycap/.venv/bin/skycap ",
                                     f"ExecStart={sys.executable} -m apps.cli "))
        out.append(copy)
    return out


def _directives(name: str) -> dict[str, list[str]]:
    d: dict[str, list[str]] = {}
    for line in (DEPLOY / name).read_text().splitlines():
        if "=" in line and not line.lstrip().startswith("#"):
            k, v = line.split("=", 1)
            d.setdefault(k.strip(), []).append(v.strip())
    return d


@pytest.mark.parametrize("name", UNITS)
def test_units_speak_the_notify_protocol_with_a_watchdog(name):
    d = _directives(name)
    assert d["Type"] == ["notify"] and d["NotifyAccess"] == ["main"]
    watchdog_s = int(d["WatchdogSec"][0].rstrip("s"))
    assert 5 <= watchdog_s <= 60 and int(d["TimeoutStartSec"][0]) >= 30
    assert d["Restart"][0] in ("on-failure", "always")  # both restart after a watchdog timeout
    assert d["CapabilityBoundingSet"] == [""] and d["SystemCallFilter"] == ["@system-service"]
    if name == "skycap-agent.service":
        # a slow autopilot: the whole connect timeout fits in the start timeout
        assert int(d["TimeoutStartSec"][0]) > AgentConfig().connect_timeout_s


@needs_systemd_analyze
def test_systemd_analyze_verifies_the_units(tmp_path):
    copies = _installable_copies(tmp_path)
    r = subprocess.run([SYSTEMD_ANALYZE, "verify", *map(str, copies)], capture_output=True, text=True, timeout=60,
                       cwd=tmp_path)
    # verify exits 0 on unknown keys and bad values ("ignoring"): any output is a finding
    assert r.returncode == 0 and not (r.stdout + r.stderr).strip(), r.stdout + r.stderr


@needs_systemd_analyze
def test_systemd_analyze_security_rates_the_units_ok(tmp_path):
    for copy in _installable_copies(tmp_path):
        r = subprocess.run([SYSTEMD_ANALYZE, "security", "--offline=yes", "--no-pager", str(copy)],
                           capture_output=True, text=True, timeout=60, cwd=tmp_path)
        if "--offline" in r.stderr and r.returncode != 0:
            pytest.skip(f"this systemd-analyze has no offline security check: {r.stderr.strip()[:120]}")
        m = re.search(r"Overall exposure level for \S+: ([0-9.]+)", r.stdout)
        assert m, r.stdout + r.stderr
        # 0 = fully confined ... 10 = unprotected (the units scored 8.5 before their hardening)
        assert float(m.group(1)) <= 3.0, r.stdout
