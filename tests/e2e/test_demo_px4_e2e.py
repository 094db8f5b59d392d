"""``skycap demo --autopilot px4`` end to end, short: real PX4 SITL (SIH) from ``../shared/px4-sitl``, camera nodes
rendering from SIH's truth, the agents over MAVSDK, reconstruction; checks that summary.json names the autopilot
and holds sane figures measured against SIH's truth.

Skipped when the PX4 SITL build is absent. PX4 instance numbers from ``$SKYCAP_PX4_FIRST_INSTANCE`` (default 0;
instance i uses MAVLink UDP 14540 + i), so that this test can run beside another PX4 fleet on one machine."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import pytest

from tests.helpers.ports import free_tcp_port

from apps.demo import DemoConfig, run_demo
from skycap.config import ConfigError
from skycap.errors import SkycapError


def _px4_folder():
    from simulator.px4_sitl import Px4SitlError, find_px4_folder

    try:
        return find_px4_folder()
    except Px4SitlError as e:
        pytest.skip(f"PX4 SITL is not available ({e})")


@pytest.mark.slow
def test_short_px4_demo_produces_a_sane_summary(tmp_path):
    folder = _px4_folder()
    first = int(os.environ.get("SKYCAP_PX4_FIRST_INSTANCE", "0"))
    out = tmp_path / "flight"
    cmd = [sys.executable, "-m", "apps.cli", "demo", "--autopilot", "px4", "--px4-dir", str(folder), "--drones", "2",
           "--duration", "20", "--out", str(out), "--set", f"px4_first_instance={first}",
           "--set", f"zenoh_endpoint=\"tcp/127.0.0.1:{free_tcp_port()}\"", "--set", "fleet=\"px4test\"",
           # the reconstruction from the simulator's keypoints: the keypoint models are tested on the built-in fleet
           "--set", 'reconstruct_keypoints="sim"']
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=420)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-5000:]
    for name in ("drone_1.s001.mcap", "drone_2.s001.mcap", "truth.mcap", "plan.json", "summary.json"):
        assert (out / name).exists(), name
    # PX4's own consoles are kept with the flight's logs
    assert (out / "logs" / "sim" / "px4" / f"instance_{first}" / "out.log").is_file()
    s = json.loads((out / "summary.json").read_text())
    ap = s["autopilot"]
    assert ap["kind"] == "px4_sitl" and ap["px4_dir"] == str(folder) and ap["instances"] == [first, first + 1], ap
    assert set(s["drones"]) == {"drone_1", "drone_2"}
    for d, row in s["drones"].items():
        # every figure finite (the row also says how the drone's flight ended and its last health)
        figures = [v for v in row.values() if isinstance(v, (int, float)) and not isinstance(v, bool)]
        assert len(figures) > 10 and all(math.isfinite(v) for v in figures), row
        assert row["ended"] == "landed by the final land command", row
        assert row["setpoint_rate_hz"] >= 10.0 and row["state_rate_hz"] >= 20.0, row
        assert row["frames_recorded"] > 50 and row["image_rate_hz"] > 3.0, row
        # loose: against SIH's truth (altitude reference and take-off handling of PX4 are the agent's business)
        assert row["orbit_radius_rmse_m"] < 2.5 and row["altitude_rmse_m"] < 3.0, row
        assert row["phase_spacing_error_deg_rms"] < 15.0, row
    f = s["fleet"]
    assert f["min_separation_m"] > f["configured_min_separation_m"]
    assert 20.0 < f["flight_s"] < 150.0 and f["steady_orbit_s"] > 5.0, f
    rec = s["reconstruction"]
    assert rec["ran"] and rec["exit_code"] == 0, rec
    assert rec["accuracy_vs_truth"]["frames_scored_window"] > 0, rec


def test_px4_demo_without_px4_is_a_clear_error_and_makes_nothing(tmp_path):
    out = tmp_path / "flight"
    cfg = DemoConfig(autopilot="px4", px4_dir=str(tmp_path / "no-px4"), out=str(out)).validate()
    with pytest.raises(SkycapError) as e:
        run_demo(cfg)
    assert "--px4-dir" in str(e.value) and "../shared/px4-sitl" in str(e.value)
    assert not out.exists()


@pytest.mark.parametrize("kw, text", [
    (dict(faults={"gps_jump_drone": "drone_1"}), "gps_jump_drone"),
    (dict(sim_set=["estimator.pos_bias_std_xy_m=0.02"]), "origin"),
    (dict(mavlink_base=14620), "px4_first_instance"),
    (dict(px4_first_instance=9, drones=2), "0..8"),
])
def test_px4_demo_refuses_what_only_the_builtin_simulator_has(kw, text):
    from skycap.config import load_config

    overrides = ['autopilot="px4"']
    for k, v in kw.items():
        if isinstance(v, dict):
            overrides += [f'{k}.{kk}="{vv}"' for kk, vv in v.items()]
        elif isinstance(v, list):
            overrides.append(f"{k}=[" + ", ".join(f'"{x}"' for x in v) + "]")
        else:
            overrides.append(f"{k}={v}")
    with pytest.raises(ConfigError, match=text):
        load_config(DemoConfig, None, overrides).validate()


def test_builtin_demo_refuses_px4_options_and_bad_sorties():
    with pytest.raises(ConfigError, match="px4"):
        DemoConfig(px4_first_instance=6).validate()
    with pytest.raises(ConfigError, match="sorties"):
        DemoConfig(sorties=0).validate()
    assert DemoConfig(sorties=2).validate().autopilot == "builtin"


def test_later_sortie_slots_turn_to_where_the_drones_are():
    """After an orbit the drones land half a circle on; a second plan with the first slots would make them cross
    the circle (and each other): the slots are turned together, spacing kept."""
    from apps.demo import _slots_where_they_are

    slots = {"drone_1": 0.0, "drone_2": math.pi}
    turned = _slots_where_they_are(slots, {"drone_1": (-8.2, -0.5, 0.0), "drone_2": (8.5, 0.4, 0.0)}, (0.0, 0.0, 0.0))
    gap = math.remainder(turned["drone_2"] - turned["drone_1"], 2 * math.pi)
    assert abs(abs(gap) - math.pi) < 1e-9  # spacing kept
    assert abs(math.remainder(turned["drone_1"] - math.pi, 2 * math.pi)) < 0.1  # drone_1's slot is where it is
    same = _slots_where_they_are(slots, {"drone_1": (8.0, 0.0, 0.0), "drone_2": (-8.0, 0.0, 0.0)}, (0.0, 0.0, 0.0))
    assert same == pytest.approx(slots, abs=1e-9)
