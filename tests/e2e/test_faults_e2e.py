"""``skycap demo --mode track`` under faults, end to end (issue 6, "Done means": the figures hold within stated
margins under faults). Short flights (2 drones, 3 for the killed agent) on real processes: simulator, camera
nodes, agents over Zenoh and MAVLink. Faults are injected by the demo's ``faults.*`` options (the transport's
receive-side fault layer, the simulator's estimator, SIGKILL, a publisher of malformed detections).

Margins (this is a loaded 2-core CI box; GPS-grade position estimates, ~1 m bias per drone): the nominal e2e
test's bounds plus a margin -- per surviving drone ``target_rmse_m`` < 2.5 m (nominal bound 2.0),
``person_in_roi_rate`` > 0.5 (nominal 0.6), ``detector_hz`` > 3; fleet ``tracking_lost_s`` < 5 s and
``min_separation_m`` above the configured limit (no margin: that one is hard). Flights that do not interfere
share one run (delay + malformed detections); each fault has its own test function.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.ports import free_tcp_port, free_udp_base

pytestmark = pytest.mark.slow

RMSE_MAX_M = 2.5
ROI_MIN = 0.5
LOST_MAX_S = 5.0


def _fly(tmp_path_factory, name: str, drones: int, duration_s: float, *sets: str) -> tuple[Path, dict, str]:
    out = tmp_path_factory.mktemp(name) / "flight"
    cmd = [sys.executable, "-m", "apps.cli", "demo", "--mode", "track", "--drones", str(drones), "--duration",
           str(duration_s), "--out", str(out), "--set", f"zenoh_endpoint=\"tcp/127.0.0.1:{free_tcp_port()}\"",
           "--set", f"mavlink_base={free_udp_base(drones)}", "--set", f"fleet=\"fault{name}\"", "--set", "reconstruct=false"]
    for s in sets:
        cmd += ["--set", s]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-5000:]
    return out, json.loads((out / "summary.json").read_text()), r.stdout


def _stats(out: Path, d: str) -> dict:
    return json.loads((out / f"{d}.s001.track.json").read_text())


def _assert_tracking(summary: dict, drones: list[str]) -> None:
    tr = summary["tracking"]
    for d in drones:
        row = tr["drones"][d]
        assert row["agent_stats"], row
        assert math.isfinite(row["target_rmse_m"]) and row["target_rmse_m"] < RMSE_MAX_M, (d, row)
        assert row["person_in_roi_rate"] > ROI_MIN, (d, row)
        assert row["detector_hz"] > 3.0, (d, row)
    f = tr["fleet"]
    assert f["tracking_lost_s"] < LOST_MAX_S, f
    assert f["min_separation_m"] > f["configured_min_separation_m"], f


@pytest.fixture(scope="module")
def dropped(tmp_path_factory):
    return _fly(tmp_path_factory, "drop", 2, 22, "faults.drop_prob=0.3")


@pytest.fixture(scope="module")
def delayed_and_malformed(tmp_path_factory):
    return _fly(tmp_path_factory, "delay", 2, 22, "faults.detection_delay_s=0.2", "faults.malformed_detections_hz=4")


@pytest.fixture(scope="module")
def gps_jump(tmp_path_factory):
    return _fly(tmp_path_factory, "jump", 2, 22, 'faults.gps_jump_drone="drone_2"', "faults.gps_jump_at_s=10",
                "faults.gps_jump_ned_m=[3.0, 0.0, 0.0]")


@pytest.fixture(scope="module")
def killed(tmp_path_factory):
    return _fly(tmp_path_factory, "kill", 3, 24, 'faults.kill_agent="drone_3"', "faults.kill_agent_at_s=8")


def test_30_percent_of_teammate_messages_dropped(dropped):
    out, s, _ = dropped
    _assert_tracking(s, ["drone_1", "drone_2"])
    for d in ("drone_1", "drone_2"):
        row = s["tracking"]["drones"][d]
        assert row["fault_judged"] > 500, row
        share = row["fault_dropped"] / row["fault_judged"]
        assert 0.25 < share < 0.35, (d, share, row)
        st = _stats(out, d)
        assert st["teammate_plans_received"] > 50, st["teammate_plans_received"]  # ~70 % of ~20 Hz still arrive
        # 30 % loss is not a lost teammate: no re-spacing
        assert "respace" not in st["failsafe_counts"], st["failsafe_events"]


def test_200_ms_delay_on_teammates_detections(delayed_and_malformed):
    out, s, _ = delayed_and_malformed
    _assert_tracking(s, ["drone_1", "drone_2"])
    for d in ("drone_1", "drone_2"):
        row = s["tracking"]["drones"][d]
        assert row["fault_delayed"] > 50 and row["fault_dropped"] == 0, row
        fs = _stats(out, d)["filter_stats"]
        # late teammate detections were re-filtered in time order, not dropped
        assert row["filter_refiltered"] > 20, fs
        assert fs["too_late"] < 0.05 * fs["accepted"], fs


def test_malformed_detections_are_ignored_and_counted(delayed_and_malformed):
    out, s, _ = delayed_and_malformed
    _assert_tracking(s, ["drone_1", "drone_2"])
    injected = s["faults"]["malformed_detections_injected"]
    assert min(injected.values()) >= 5, injected
    # drone_1 gets all four kinds (two on its own detector key, two as drone_2's shared detections)
    m1 = _stats(out, "drone_1")["malformed_detections"]
    assert m1["refused_by_codec"] >= 0.8 * (injected["nan_box"] + injected["nan_pose"]), (m1, injected)
    assert m1["invalid_content"] >= 0.8 * (injected["inverted_box"] + injected["non_rigid_pose"]), (m1, injected)
    assert s["tracking"]["drones"]["drone_1"]["malformed_detections"] == m1["total"]
    # drone_2 sees the NaN pose on its own shared key (refused by the codec); it ignores its own key otherwise
    m2 = _stats(out, "drone_2")["malformed_detections"]
    assert m2["refused_by_codec"] >= 0.8 * injected["nan_pose"], (m2, injected)
    # nothing malformed reached the filters
    for d in ("drone_1", "drone_2"):
        assert _stats(out, d)["filter_stats"]["rejected_nonfinite"] == 0


def test_sudden_3_m_gps_jump_on_one_drone(gps_jump):
    out, s, _ = gps_jump
    _assert_tracking(s, ["drone_1", "drone_2"])
    assert "SIMULATED GPS JUMP" in (out / "logs" / "sim.log").read_text()
    # drone_2's agent noticed the jump of its reported position (and only it) and took it back from its poses
    jumps = {d: [e for e in _stats(out, d)["failsafe_events"] if e["action"] == "gps_jump"] for d in ("drone_1", "drone_2")}
    assert len(jumps["drone_2"]) == 1 and not jumps["drone_1"], jumps
    # drone_2's own-position correction (filter offset + the detected step) takes the jump (north: ~+3 m)
    st = _stats(out, "drone_2")
    t_jump_ns = (json.loads((out / "plan.json").read_text())["start_time_ns"] + 10e9)
    off = [r for r in st["offset_log"]]
    before = [r[1] for r in off if t_jump_ns - 4e9 <= r[0] < t_jump_ns]
    after = [r[1] for r in off if r[0] >= t_jump_ns + 6e9]
    assert before and after
    shift = sum(after) / len(after) - sum(before) / len(before)
    assert shift > 2.0, (shift, st["filter_stats"])
    # its own position corrected by that offset: most of the 3 m error is gone
    row = s["tracking"]["drones"]["drone_2"]
    assert row["self_pos_err_m_after"] < 0.5 * row["self_pos_err_m_before"], row


def test_killed_agent_the_others_respace(killed):
    out, s, _ = killed
    survivors = ["drone_1", "drone_2"]
    _assert_tracking(s, survivors)
    k = s["faults"]["agent_killed"]
    assert k["drone"] == "drone_3"
    assert not s["tracking"]["drones"]["drone_3"]["agent_stats"]  # killed: it wrote no statistics
    plan = json.loads((out / "plan.json").read_text())
    slots = {}
    for d in survivors:
        ev = [e for e in _stats(out, d)["failsafe_events"] if e["action"] == "respace"]
        assert ev, _stats(out, d)["failsafe_events"]
        e = ev[0]
        assert e["present"] == survivors and "drone_3" in " ".join(e["reasons"]), e
        assert 0.0 < e["t_s"] - k["t_s"] < 6.0, (e, k)  # noticed within the teammate timeout (+ load)
        delta = (e["slot_angle_rad"] - plan["phase_offset_rad"][d] + math.pi) % (2 * math.pi) - math.pi
        assert abs(delta) > math.radians(10), (d, e, plan["phase_offset_rad"])  # its slot moved
        slots[d] = e["slot_angle_rad"]
    gap = abs((slots["drone_1"] - slots["drone_2"] + math.pi) % (2 * math.pi) - math.pi)
    assert abs(gap - math.pi) < math.radians(5), slots  # two drones left: opposite sides of the person
