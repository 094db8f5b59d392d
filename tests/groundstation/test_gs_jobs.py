"""The ground station's "process flight" job (groundstation.app.jobs.ProcessFlightJob) over a real jobs runner
(reconstruction.jobs.LocalRunner: a spawned worker process) running a stand-in processor with the pipeline's shape
(tests/groundstation/fake_process.py); the real pipeline runs in the self-test test. And the flight list."""

from __future__ import annotations

import json

import pytest

from flightdata.folder import FlightFolder
from groundstation.app.jobs import JobError, ProcessFlightJob, list_flights
from reconstruction.jobs import LocalRunner

FAKE = "tests.groundstation.fake_process:run"


@pytest.fixture(scope="module")
def runner():
    with LocalRunner(workers=1, threads_per_worker=1, cancel_grace_s=5) as r:
        yield r


def _job(runner, flight, *opts) -> ProcessFlightJob:
    flight.mkdir(exist_ok=True)
    return ProcessFlightJob(runner.submit(flight, list(opts), processor=FAKE), FlightFolder(flight))


def test_job_progress_over_the_steps_log_and_result(runner, tmp_path):
    job = _job(runner, tmp_path / "f1", "step_s=0.1")
    seen = []
    while not job.wait(0.05):
        seen.append((job.progress()[1], job.fraction()))
    fracs = [f for _, f in seen]
    assert fracs == sorted(fracs) and 0.0 < max(fracs) < 1.0, seen  # one bar over the steps, never backwards
    assert any(stage.startswith("fitting the body model") for stage, _ in seen), seen
    state, stage, elapsed = job.progress()
    assert state == "done" and job.fraction() == 1.0 and elapsed > 1.0
    res = job.result()
    assert res["summary"]["cameras"] == 2 and res["method"] == "multiview"
    assert res["outputs"]["bvh"][0].endswith("motion.bvh") and "summary.json" in res["outputs"]["files"]
    assert [line.split("step ")[1].split(":")[0] for line in job.log() if "step " in line] == \
        ["boxes", "keypoints", "fit", "export"]


def test_job_failure_is_an_error_naming_the_cause(runner, tmp_path):
    job = _job(runner, tmp_path / "f2", "fail=1")
    assert job.wait(60)
    assert job.progress()[0] == "failed"
    with pytest.raises(JobError, match="ValueError: the fit diverged"):
        job.result()


def test_job_cancel(runner, tmp_path):
    job = _job(runner, tmp_path / "f3", "step_s=1.0")
    while job.progress()[0] != "running":
        job.wait(0.05)
    job.cancel()
    assert job.wait(30)
    assert job.progress()[0] == "cancelled" and job.result() is None


def test_submit_refuses_a_folder_without_recordings_and_lists_flights(runner, tmp_path):
    with pytest.raises(JobError, match="no drone recording"):
        ProcessFlightJob.submit(tmp_path, runner)
    f = tmp_path / "flights" / "a"
    f.mkdir(parents=True)
    (f / "drone_1.s001.mcap").write_bytes(b"x" * 10)
    (tmp_path / "flights" / "not-a-flight").mkdir()
    flights = list_flights(tmp_path / "flights")
    assert [x["name"] for x in flights] == ["a"] and flights[0]["drones"] == ["drone_1"]
    assert flights[0]["processed"] == [] and json.dumps(flights)
