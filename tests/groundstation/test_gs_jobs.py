"""The ground station's job interface (submit / progress / log / cancel / result) over stand-in processes, and the
flight list; the real ``skycap reconstruct`` runs in the self-test test."""

from __future__ import annotations

import json
import sys
import time
import textwrap

import pytest

from groundstation.app.jobs import JobError, ReconstructJob, list_flights


def _script(tmp_path, body: str) -> list[str]:
    p = tmp_path / "fake_reconstruct.py"
    p.write_text(textwrap.dedent(body))
    return [sys.executable, str(p)]


def test_job_progress_log_and_result(tmp_path):
    flight = tmp_path / "f1"
    flight.mkdir()
    cmd = _script(tmp_path, f"""
        import json, pathlib, time
        print("2026-01-01 00:00:00,000 INFO reconstruction.flight: read the whole flight of X", flush=True)
        time.sleep(0.6)
        print("2026-01-01 00:00:01,000 INFO reconstruction.multiview.run: multiview fit (product) of 2 cameras", flush=True)
        time.sleep(0.6)
        d = pathlib.Path({str(flight)!r}) / "reconstruction"
        d.mkdir()
        (d / "motion.bvh").write_text("HIERARCHY")
        (d / "summary.json").write_text(json.dumps({{"frames": 7, "cameras": 2}}))
        print("2026-01-01 00:00:02,000 INFO reconstruction.multiview.run: wrote motion.bvh", flush=True)
    """)
    job = ReconstructJob(flight, cmd)
    seen = set()
    while job.progress()[0] == "running":
        seen.add((job.progress()[1], job.fraction()))
        time.sleep(0.05)
    assert job.wait(10)
    assert ("fitting the body model", 0.3) in seen, seen
    state, stage, elapsed = job.progress()
    assert state == "done" and job.fraction() == 1.0 and elapsed > 1.0
    res = job.result()
    assert res["summary"] == {"frames": 7, "cameras": 2} and res["method"] == "multiview"
    assert res["outputs"]["bvh"][0].endswith("motion.bvh")
    assert any("wrote motion.bvh" in line for line in job.log())


def test_job_failure_is_an_error_naming_the_exit_code(tmp_path):
    job = ReconstructJob(tmp_path, _script(tmp_path, "import sys; print('boom'); sys.exit(3)"))
    assert job.wait(10)
    assert job.progress()[0] == "failed"
    with pytest.raises(JobError, match="exited with code 3.*boom"):
        job.result()


def test_job_cancel(tmp_path):
    job = ReconstructJob(tmp_path, _script(tmp_path, "import time; time.sleep(30)"))
    job.cancel()
    assert job.wait(10)
    assert job.progress()[0] == "cancelled" and job.result() is None


def test_submit_refuses_a_folder_without_recordings_and_lists_flights(tmp_path):
    with pytest.raises(JobError, match="no drone recording"):
        ReconstructJob.submit(tmp_path)
    f = tmp_path / "flights" / "a"
    f.mkdir(parents=True)
    (f / "drone_1.s001.mcap").write_bytes(b"x" * 10)
    (tmp_path / "flights" / "not-a-flight").mkdir()
    flights = list_flights(tmp_path / "flights")
    assert [x["name"] for x in flights] == ["a"] and flights[0]["drones"] == ["drone_1"]
    assert flights[0]["processed"] == [] and json.dumps(flights)
