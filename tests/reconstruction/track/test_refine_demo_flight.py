"""``skycap refine`` on a real recorded flight: a short ``skycap demo --mode track`` (simulator, cameras, agents
with the live cooperative filters), then the offline smoother against truth.mcap and the live estimates."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

from tests.helpers.ports import free_tcp_port, free_udp_base

pytestmark = pytest.mark.slow


@pytest.fixture(scope="session")
def track_flight(tmp_path_factory):
    out = tmp_path_factory.mktemp("refine_demo") / "track"
    cmd = [sys.executable, "-m", "apps.cli", "demo", "--mode", "track", "--drones", "2", "--duration", "18",
           "--out", str(out), "--set", f"zenoh_endpoint=\"tcp/127.0.0.1:{free_tcp_port()}\"",
           "--set", f"mavlink_base={free_udp_base(2)}", "--set", "fleet=\"refinetest\"", "--set", "reconstruct=false"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-5000:]
    return out


def test_refine_a_recorded_track_flight(track_flight):
    from apps.cli import main

    assert main(["refine", str(track_flight)]) == 0
    s = json.loads((track_flight / "refined_track.json").read_text())
    assert s["drones"] == ["drone_1", "drone_2"]
    assert set(s["detections_topic"].values()) == {"detections"}
    assert s["person_height_m"] == pytest.approx(1.95)  # from the demo's config.toml
    assert s["frames_used"] > 100 and s["frames_rejected"] < 0.2 * s["frames"], s
    f = s["evaluation"]["fleet"]
    # GPS-grade drones (~1 m offset each): loose bounds; the smoother must not be worse than the live filters
    assert f["person_rmse_m_smoothed"] < 1.5, f
    assert math.isfinite(f["person_rmse_m_live"])
    assert f["person_rmse_fleet_frame_m_smoothed"] < f["person_rmse_fleet_frame_m_live"] + 0.1, f
    for d, row in s["evaluation"]["drones"].items():
        assert row["roi_frames"] > 30 and row["person_in_roi_rate_smoothed"] > 0.9, (d, row)
        assert math.isfinite(row["position_err_m_refined"]), (d, row)
