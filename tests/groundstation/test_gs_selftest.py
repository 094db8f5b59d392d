"""``skycap gs --selftest DIR``: the whole scripted operator session (two simulated drones, a short orbit, process
flight) in its own process; then the reconstruction job's cancel on the flight it recorded."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

pytest.importorskip("PySide6")

pytestmark = pytest.mark.slow


def test_gs_selftest_whole_session_with_screenshots(tmp_path):
    out = tmp_path / "selftest"
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    r = subprocess.run([sys.executable, "-m", "apps.cli", "gs", "--selftest", str(out), "--orbit-s", "12"],
                       capture_output=True, text=True, timeout=400, env=env)
    report = json.loads((out / "selftest.json").read_text())
    names = [s["name"] for s in report["steps"]]
    assert r.returncode == 0 and report["ok"], r.stdout[-3000:] + r.stderr[-3000:]
    for want in ("fleet_up", "plan_refused_bad_field", "plan_orbit", "checklist", "takeoff_confirm", "takeoff",
                 "start", "watch_live_view", "view_3d", "watch_map", "land_all", "process_flight_result"):
        assert want in names, names
    for s in report["steps"]:
        png = out / s["screenshot"]
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000, s
    processed = report["processed"]
    assert processed["cameras"] == 2 and processed["frames"] > 0, processed
    assert report["processed_outputs"]["bvh"] and os.path.exists(report["processed_outputs"]["bvh"][0])

    # the job interface: cancel stops the reconstruction and says so (no result, no failure)
    from groundstation.app.jobs import ReconstructJob, list_flights

    flights = list_flights(out / "flights")
    assert flights and flights[0]["processed"] == ["multiview"] and flights[0]["drones"] == ["drone_1", "drone_2"]
    job = ReconstructJob.submit(flights[0]["path"], ["--mv-out", str(tmp_path / "again")])
    assert job.progress()[0] == "running"
    job.cancel()
    assert job.wait(30)
    assert job.progress()[0] == "cancelled" and job.result() is None
