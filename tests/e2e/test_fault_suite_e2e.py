"""``skycap faults run``, one short scenario per test (2 drones, the fault 10 s after the start): each flight must
stay safe (truth: separation, geofence, no landing other than by policy) and lose no recording (a crash: at most
1 s). The whole suite is the command itself (``skycap faults run --out DIR``).

Test flights are shorter than the suite's defaults (what each scenario asserts, not its length, is under test): the
orbit at 3 m instead of 6 m (take-off and landing take half as long), and the orbit only as long as the scenario
needs -- 14 s (the shortest the demo allows after its 8 s settling) for faults present from the start, 16 s for a
fault at 10 s that the drones must ride out, 20 s where the test asserts on what comes well after the fault (the
landing by policy after the 5 s heartbeat timeout, the outsider's 10 s, the full disk's > 5 s)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow


#: orbit seconds: a fault from the start / a fault at 10 s to ride out / a test of what comes > 5 s after the fault
FROM_START_S, RIDE_OUT_S, LONG_S = 14, 16, 20


def _run(tmp_path: Path, name: str, duration_s: float, *sets: str) -> tuple[dict, Path]:
    out = tmp_path / "faults"
    cmd = [sys.executable, "-m", "apps.cli", "faults", "run", "--scenario", name, "--out", str(out),
           "--set", f"demo.duration_s={duration_s}", "--set", "demo.orbit.altitude_m=3.0"]
    for s in sets:
        cmd += ["--set", s]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    report = json.loads((out / "faults.json").read_text())
    assert (out / "config.toml").is_file()
    (entry,) = report["scenarios"]
    assert entry["name"] == name and name in r.stdout  # the table
    assert r.returncode == (0 if entry["safe"] is None or (entry["safe"] and entry["recording_ok"]) else 1)
    return entry, out / name


def _assert_safe(e: dict) -> None:
    assert e["safe"] is True, (e["unsafe_because"], e["what_happened"])
    assert e["min_separation_m"] >= e["configured_min_separation_m"]
    assert not e["uncommanded_landings"] and not any(e["geofence_outside_s"].values())
    assert e["recording_ok"] is True, (e["recording_lost_s_by_drone"], e["recording_budget_s"])


def test_message_loss_30pct(tmp_path):
    e, _ = _run(tmp_path, "message_loss_30pct", FROM_START_S)
    _assert_safe(e)
    assert e["recording_lost_s"] == 0.0
    for d in ("drone_1", "drone_2"):
        fl = e["drones"][d]["fault_layer"]
        assert fl["fault_judged"] > 100 and 0.2 < fl["fault_dropped"] / fl["fault_judged"] < 0.4, fl
        assert e["drones"][d]["ended"] == "landed by the final land command"


def test_delay_200ms(tmp_path):
    e, _ = _run(tmp_path, "delay_200ms", FROM_START_S)
    _assert_safe(e)
    assert e["recording_lost_s"] == 0.0
    for d in ("drone_1", "drone_2"):
        fl = e["drones"][d]["fault_layer"]
        assert fl["fault_delayed"] > 100 and fl["fault_dropped"] == 0, fl


def test_agent_sigkill_restart_loses_at_most_1_s(tmp_path):
    e, folder = _run(tmp_path, "agent_sigkill_restart", RIDE_OUT_S)
    _assert_safe(e)
    d2 = e["drones"]["drone_2"]
    assert d2["recordings"] == ["drone_2.s001.mcap", "drone_2.s002.mcap"]  # the old file kept, a new one
    assert 0.0 < d2["recording_lost_s"] <= 1.0 and len(d2["file_seams"]) == 1, d2
    assert 9.0 < d2["file_seams"][0][0] < 11.0, d2  # the gap between the files is the crash, 10 s after the start
    assert e["drones"]["drone_1"]["recording_lost_s"] == 0.0
    r = e["launcher_faults"]["agent_restarted"]
    assert r["resume_acks"] and all(a.endswith("accepted") for a in r["resume_acks"]), r
    assert d2["ended"] == "landed by the final land command"


def test_gcs_link_lost_the_drones_land_by_policy(tmp_path):
    e, _ = _run(tmp_path, "gcs_link_lost", LONG_S)
    _assert_safe(e)
    assert e["recording_lost_s"] == 0.0
    for d in ("drone_1", "drone_2"):
        downs = e["touchdowns_after_start_s"][d]
        assert len(downs) == 1 and 14.0 < downs[0] < 30.0, downs  # 5 s heartbeat timeout, then the landing
        assert "before the final land command" in e["drones"][d]["ended"], e["drones"][d]["ended"]
        assert any("ground-station heartbeat lost" in w for w in e["drones"][d]["health_warnings"])


def test_mavlink_link_lost_3s(tmp_path):
    e, folder = _run(tmp_path, "mavlink_link_lost_3s", RIDE_OUT_S)
    _assert_safe(e)
    assert e["recording_lost_s"] == 0.0  # the camera kept being recorded
    assert e["drones"]["drone_1"]["stream_gaps_s"]["state"] >= 2.0, e["drones"]["drone_1"]  # no telemetry
    assert "SIMULATED MAVLINK LINK LOSS" in (folder / "logs" / "sim.log").read_text()
    assert e["drones"]["drone_1"]["ended"] == "landed by the final land command"


def test_gps_jump_3m(tmp_path):
    e, folder = _run(tmp_path, "gps_jump_3m", RIDE_OUT_S)
    _assert_safe(e)
    assert e["recording_lost_s"] == 0.0
    assert "SIMULATED GPS JUMP" in (folder / "logs" / "sim.log").read_text()


def test_malformed_flood_is_refused(tmp_path):
    e, _ = _run(tmp_path, "malformed_flood", FROM_START_S)
    _assert_safe(e)
    assert e["recording_lost_s"] == 0.0
    injected = e["launcher_faults"]["malformed_messages_injected"]
    assert min(injected.values()) > 50, injected
    r1 = e["drones"]["drone_1"]["refused_messages"]
    # drone_1 refused drone_2's NaN / garbage states (on its subscription to every drone's state) and every NaN /
    # garbage command; drone_2 the commands
    assert r1["*/state"]["refused"] >= 0.8 * (injected["nan_state"] + injected["garbage_state"]), r1
    assert r1["gcs/cmd"]["refused"] >= 0.8 * (injected["nan_command"] + injected["garbage_command"]), r1
    assert e["drones"]["drone_2"]["refused_messages"]["gcs/cmd"]["refused"] >= 0.8 * injected["nan_command"]


def test_outsider_without_certificate_can_neither_snoop_nor_command(tmp_path):
    e, _ = _run(tmp_path, "outsider_without_certificate", LONG_S)
    _assert_safe(e)
    o = e["launcher_faults"]["outsider"]
    assert o["commands_sent"] >= 20, o  # 10 s, twice a second, from each of its two sessions
    assert o["links"] == {"plain": 0, "foreign_ca": 0}, o
    assert o["received"] == {"plain": 0, "foreign_ca": 0}, o
    assert o["answered"] == [], o
    for d in ("drone_1", "drone_2"):
        assert e["drones"][d]["ended"] == "landed by the final land command", e["drones"][d]
    assert "outsider" in e["what_happened"]


def test_recorder_disk_full_keeps_flying_and_keeps_what_was_written(tmp_path):
    e, folder = _run(tmp_path, "recorder_disk_full", LONG_S)
    _assert_safe(e)
    d1 = e["drones"]["drone_1"]
    assert d1["recording_lost_s"] == 0.0, d1  # nothing written before the disk filled is lost
    assert d1["not_recordable_after_fault_s"] > 5.0, d1
    assert any("No space left on device" in w for w in d1["health_warnings"]), d1["health_warnings"]
    assert d1["ended"] == "landed by the final land command"
    assert e["drones"]["drone_2"]["recording_lost_s"] == 0.0


def test_recorder_killed_restarts_into_a_new_file(tmp_path):
    e, _ = _run(tmp_path, "recorder_killed", RIDE_OUT_S)
    _assert_safe(e)
    d1 = e["drones"]["drone_1"]
    assert d1["recordings"] == ["drone_1.s001.mcap", "drone_1.s002.mcap"], d1
    assert 0.0 < d1["recording_lost_s"] <= 1.0 and len(d1["file_seams"]) == 1, d1
    assert any("recorder" in w and "writer killed" in w for w in d1["health_warnings"]), d1["health_warnings"]
