"""``skycap demo`` end to end, short: a simulator process, agent processes, the fleet client; checks the
flight folder and that summary.json holds sane values (non-default ports so it can run beside a demo). The person
performs a tiny BVH (``--motion``): the truth carries it and the config and summary name it."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.helpers.bvh import write_bvh
from tests.helpers.ports import free_tcp_port, free_udp_base


pytestmark = pytest.mark.slow


def test_short_demo_produces_a_sane_summary(tmp_path):
    out = tmp_path / "flight"
    bvh = write_bvh(tmp_path / "tiny_walk.bvh")
    cmd = [sys.executable, "-m", "apps.cli", "demo", "--drones", "2", "--duration", "20", "--out", str(out),
           "--set", f"zenoh_endpoint=\"tcp/127.0.0.1:{free_tcp_port()}\"", "--set", f"mavlink_base={free_udp_base(2)}",
           "--set", "fleet=\"demotest\"", "--set", "reconstruct=false", "--motion", str(bvh)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-5000:]
    for name in ("drone_1.s001.mcap", "drone_2.s001.mcap", "truth.mcap", "config.toml", "plan.json", "summary.json", "logs"):
        assert (out / name).exists(), name
    s = json.loads((out / "summary.json").read_text())
    assert set(s["drones"]) == {"drone_1", "drone_2"}
    for d, row in s["drones"].items():
        assert row["setpoint_rate_hz"] >= 10.0, row
        assert row["state_rate_hz"] >= 45.0, row
        # tracking of the vehicle's own estimate; the truth adds the simulated GPS bias (~1 m std)
        assert row["orbit_radius_rmse_est_m"] < 0.5 and row["altitude_rmse_est_m"] < 0.3, row
        assert row["orbit_radius_rmse_m"] < 2.0 and row["altitude_rmse_m"] < 1.5, row
        assert row["phase_spacing_error_deg_rms"] < 10.0, row
        assert row["frames_recorded"] > 100 and row["image_rate_hz"] > 5.0, row  # camera default 10 Hz
    assert s["fleet"]["min_separation_m"] > s["fleet"]["configured_min_separation_m"]
    assert 25.0 < s["fleet"]["flight_s"] < 90.0
    assert "setpt_hz" in r.stdout  # the printed table
    # secure by default: mutual TLS + ACL, each command logged with its authenticated sender; no key left behind
    assert s["security"]["insecure"] is False and s["security"]["identities"]["gcs"] == "gcs", s["security"]
    agent_log = (out / "logs" / "drone_1.log").read_text()
    assert "secure transport: mutual TLS as 'drone_1'" in agent_log
    assert "command land" in agent_log and "authenticated: certificate CN 'gcs'" in agent_log
    assert not list(out.rglob("*.key")), "private keys must never land in the flight folder"
    # --motion: named with its sha256 in config.toml and summary.json; the truth's person performs it at the centre
    import hashlib
    import tomllib

    import numpy as np

    from flightdata.flightlog import FlightLog
    from shared_msgs import SimTruth

    sha = hashlib.sha256(bvh.read_bytes()).hexdigest()
    mc = tomllib.loads((out / "config.toml").read_text())["motion"]
    assert mc["file"] == str(bvh.resolve()) and mc["sha256"] == sha and mc["center_ne_m"] == [0.0, 0.0]
    m = s["motion"]
    assert m["sha256"] == sha and m["rig"] == "cmu" and m["units"] == "inches" and "played it" in m["note"], m
    truths = [t.msg for t in FlightLog(out / "truth.mcap").messages() if isinstance(t.msg, SimTruth)]
    assert truths and all(t.person_motion == "bvh:tiny_walk" for t in truths[::50])
    hips = np.array([np.reshape(t.person_joints_ned_m, (17, 3))[11:13].mean(axis=0) for t in truths[::10]])
    # walks east about the centre (1 m in 0.97 s, looped with a 0.32 s seam: 0.65 m between two seams)
    assert np.abs(hips[:, :2]).max() < 0.6 and np.ptp(hips[:, 1]) > 0.5

    # a second demo into the same folder is refused before it starts anything, and changes no file
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    r2 = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r2.returncode == 2 and "never overwritten" in r2.stderr and "--out" in r2.stderr, r2.stderr[-2000:]
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
