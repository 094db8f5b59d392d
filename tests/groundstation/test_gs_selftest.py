"""``skycap gs --selftest DIR``: the whole scripted operator session (two simulated drones, a short orbit, process
flight) in its own process; then the reconstruction job's cancel on the flight it recorded. ``--sim-mode track``: the
session with a tracking formation (agents in track mode; no processing)."""

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
    # a 6 s orbit (as the tracking session's below): the steps during the orbit wait for what they show, and the
    # processing of a shorter flight is shorter
    r = subprocess.run([sys.executable, "-m", "apps.cli", "gs", "--selftest", str(out), "--orbit-s", "6"],
                       capture_output=True, text=True, timeout=400, env=env)
    report = json.loads((out / "selftest.json").read_text())
    names = [s["name"] for s in report["steps"]]
    assert r.returncode == 0 and report["ok"], r.stdout[-3000:] + r.stderr[-3000:]
    for want in ("fleet_up", "plan_refused_bad_field", "plan_refused_keepout", "plan_track_refused_by_orbit_agents",
                 "plan_orbit", "checklist", "takeoff_confirm", "takeoff", "start", "watch_live_view", "view_3d",
                 "watch_map", "land_all", "process_flight_result"):
        assert want in names, names
    by_name = {s["name"]: s for s in report["steps"]}
    assert "keep-out zone 'shed'" in by_name["plan_refused_keepout"]["detail"]
    assert by_name["plan_track_refused_by_orbit_agents"]["detail"].count("wrong mode") == 2
    for s in report["steps"]:
        png = out / s["screenshot"]
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000, s
    processed = report["processed"]
    assert processed["cameras"] == 2 and processed["frames"] > 0, processed
    assert report["processed_outputs"]["bvh"] and os.path.exists(report["processed_outputs"]["bvh"][0])

    # the job interface: cancel stops the processing and says so (no result, no failure)
    from groundstation.app.jobs import ProcessFlightJob, list_flights
    from reconstruction.jobs import LocalRunner

    flights = list_flights(out / "flights")
    assert flights and flights[0]["processed"] == ["multiview"] and flights[0]["drones"] == ["drone_1", "drone_2"]
    with LocalRunner(workers=1, threads_per_worker=1, cancel_grace_s=10) as runner:
        job = ProcessFlightJob.submit(flights[0]["path"], runner, [f'out_dir="{tmp_path / "again"}"'])
        assert job.progress()[0] in ("queued", "running")
        job.cancel()
        assert job.wait(60)
        assert job.progress()[0] == "cancelled" and job.result() is None


def test_gs_selftest_tracking_formation(tmp_path):
    """The session with the simulated agents in track mode: the tracking formation is planned (a slot in the keep-out
    zone refused first), flown, and every drone's fused person estimate shows live in the tracker column, near the
    simulator's truth."""
    out = tmp_path / "selftest-track"
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    r = subprocess.run([sys.executable, "-m", "apps.cli", "gs", "--selftest", str(out), "--sim-mode", "track",
                        "--orbit-s", "6", "--no-process"], capture_output=True, text=True, timeout=300, env=env)
    report = json.loads((out / "selftest.json").read_text())
    assert r.returncode == 0 and report["ok"], r.stdout[-3000:] + r.stderr[-3000:]
    names = [s["name"] for s in report["steps"]]
    for want in ("fleet_up", "plan_refused_keepout", "plan_track", "takeoff", "start", "watch_tracking", "view_3d",
                 "land_all", "flight_ended"):
        assert want in names, names
    assert report["mode"] == "track"
    cells = report["tracking"]["tracker_cells"]
    assert sorted(cells) == ["drone_1", "drone_2"] and all(c.startswith("tracking") for c in cells.values()), cells
    assert max(report["tracking"]["horizontal_error_to_truth_m"].values()) < 3.0
    for s in report["steps"]:
        png = out / s["screenshot"]
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000, s
