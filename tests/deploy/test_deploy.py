"""The deployment files: the example config loads and validates, the systemd unit runs the agent with it."""

from pathlib import Path

from onboard.config import AgentConfig
from skycap.config import load_config
from tests.helpers.paths import REPO

DEPLOY = REPO / "deploy"


def test_example_config_loads_and_validates():
    cfg = load_config(AgentConfig, DEPLOY / "agent.example.toml").validate()
    assert cfg.drone_id == "drone_1" and cfg.connection.startswith("serial://")
    assert cfg.safety.sigterm_action == "land"


def test_systemd_unit_runs_the_agent_and_leaves_time_to_land():
    unit = (DEPLOY / "skycap-agent.service").read_text()
    assert "ExecStart=/opt/skycap/.venv/bin/skycap agent --config /etc/skycap/agent.toml" in unit
    timeout = int(next(l for l in unit.splitlines() if l.startswith("TimeoutStopSec=")).split("=")[1])
    assert timeout > AgentConfig().safety.sigterm_land_timeout_s
