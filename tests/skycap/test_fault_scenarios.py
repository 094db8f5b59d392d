"""The fault suite's scenario registry and report, without flying: every scenario's overrides make a valid demo
configuration that differs from the base (the fault is really set), a scenario that cannot run yet is reported
with "safe": null, the table."""

from __future__ import annotations

import dataclasses

import pytest

from apps.faults import SCENARIOS, FaultsConfig, format_faults_table, run_scenario, scenario_demo_config
from skycap.config import ConfigError


@pytest.mark.parametrize("drones", [2, 3])
@pytest.mark.parametrize("name", [n for n, s in SCENARIOS.items() if not s.not_run])
def test_each_scenario_is_a_valid_demo_configuration_with_its_fault_set(tmp_path, name, drones):
    cfg = FaultsConfig(free_ports=False)
    cfg.demo = dataclasses.replace(cfg.demo, drones=drones)
    d = scenario_demo_config(cfg.validate(), SCENARIOS[name], tmp_path / name)
    assert d.out == str(tmp_path / name) and d.drones == drones
    assert d.faults != cfg.demo.faults or d.agent_set != cfg.demo.agent_set, name
    ids = [f"drone_{i + 1}" for i in range(drones)]
    for v in (d.faults.kill_agent, d.faults.gps_jump_drone, d.faults.mavlink_loss_drone, d.faults.recorder_fault_drone):
        assert v in ("", ids[0], ids[-1])


def test_a_scenario_that_cannot_run_says_why_and_flies_nothing(tmp_path):
    from apps.faults import Scenario

    e = run_scenario(FaultsConfig(), Scenario("later", "a fault not built yet", not_run="not run: needs X"), tmp_path / "x")
    assert e["safe"] is None and e["recording_lost_s"] is None and e["what_happened"].startswith("not run")
    assert not (tmp_path / "x").exists()


def test_unknown_scenario_and_bad_limits_are_refused():
    with pytest.raises(ConfigError, match="unknown scenario"):
        FaultsConfig(scenarios=["nope"]).validate()
    with pytest.raises(ConfigError):
        FaultsConfig(geofence_radius_m=0).validate()


def test_the_table_has_a_row_per_scenario():
    rep = {"scenarios": [
        {"name": "a", "safe": True, "min_separation_m": 15.0, "recording_lost_s": 0.4, "recording_ok": True,
         "what_happened": "x", "drones": {"drone_1": {"refused_messages": {"gcs/cmd": {"refused": 7}}}}},
        {"name": "b", "safe": None, "recording_lost_s": None, "recording_ok": None, "what_happened": "not run: y"},
        {"name": "c", "safe": False, "min_separation_m": 2.0, "recording_lost_s": 3.0, "recording_ok": False,
         "what_happened": "UNSAFE", "drones": {}}]}
    lines = format_faults_table(rep).splitlines()
    assert len(lines) == 4 and lines[1].split()[:6] == ["a", "yes", "15.0", "0.40", "yes", "7"]
    assert lines[2].split()[:2] == ["b", "-"] and lines[3].split()[:2] == ["c", "NO"]
