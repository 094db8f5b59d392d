"""The local runner with a real processor (numpy steps cached in the flight folder) in real worker processes."""

from __future__ import annotations

import time

import numpy as np
import pytest

from reconstruction.jobs import JobCancelled, JobFailed, JobStatus, LocalRunner, ProgressEvent
from tests.reconstruction.jobs.stepjob import CACHE, StepConfig, StepFailure, StepResult, make_flight, step_path

STEP = "tests.reconstruction.jobs.stepjob:step_job"


@pytest.fixture(scope="module")
def runner():
    r = LocalRunner(workers=2, threads_per_worker=1, cancel_grace_s=20)
    yield r
    r.close()


def _wait_for(pred, timeout_s=60.0, what=""):
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if pred():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def test_job_runs_and_reports_events_in_order(runner, tmp_path):
    flight = make_flight(tmp_path / "f", seed=1)
    seen: list[ProgressEvent] = []
    job = runner.submit(flight, StepConfig(steps=3, units=2), processor=STEP)
    job.subscribe(seen.append)
    res = job.result(timeout=120)
    assert job.status is JobStatus.DONE and job.done() and str(job.status) == "done"
    assert isinstance(res, StepResult) and res.computed == [0, 1, 2] and res.cached == []
    # ran in a worker process, not here
    assert res.pid == job.worker["pid"] and res.pid != __import__("os").getpid()
    # the events arrived in the order the processor made them: per step start, then units 1/2, 2/2
    expected = [(f"step{k}", f) for k in range(3) for f in (0.0, 0.5, 1.0)]
    assert [(e.step, e.fraction) for e in job.events] == expected
    assert [(e.step, e.fraction) for e in seen] == expected
    assert [(e.step, e.fraction) for e in job.iter_events(timeout=5)] == expected
    assert all(b.elapsed_s >= a.elapsed_s for a, b in zip(job.events, job.events[1:]))
    assert job.progress == job.events[-1] and job.elapsed_s > 0
    # the result is the processor's, computed there: recompute here and compare
    from tests.reconstruction.jobs.stepjob import step_job
    import threading

    again = step_job(make_flight(tmp_path / "g", seed=1), StepConfig(steps=3, units=2), lambda e: None,
                     threading.Event())
    np.testing.assert_allclose(res.state, again.state, rtol=1e-9, atol=1e-12)


def test_cancel_stops_a_running_job_and_leaves_the_cache_consistent(runner, tmp_path):
    flight = make_flight(tmp_path / "f", seed=2)
    cfg = StepConfig(steps=40, units=2, iters=150)
    job = runner.submit(flight, cfg, processor=STEP)
    _wait_for(lambda: any(e.step == "step1" for e in job.events), what="step 1 started")
    assert job.status is JobStatus.RUNNING
    assert job.cancel() is True
    assert job.wait(60), "the worker did not stop after cancel"
    assert job.status is JobStatus.CANCELLED
    assert "StepCancelled" in job.message or "JobCancelled" in job.message  # stopped by itself, not terminated
    with pytest.raises(JobCancelled):
        job.result(timeout=1)
    assert job.cancel() is False
    # the worker stopped: nothing more is written
    files = sorted((flight / CACHE).iterdir())
    time.sleep(1.0)
    assert sorted((flight / CACHE).iterdir()) == files
    # the cache: whole steps only, no partial file, fewer than all
    assert files and all(p.suffix == ".npz" for p in files), files
    n_cached = len(files)
    assert 1 <= n_cached < cfg.steps
    assert files == [step_path(flight, k) for k in range(n_cached)]
    for p in files:
        assert np.load(p)["state"].shape == (96, 96)
    # resume: the cached steps are not recomputed and the result equals an uninterrupted run
    res = runner.submit(flight, StepConfig(steps=n_cached + 2, units=2, iters=150), processor=STEP).result(120)
    assert res.cached == list(range(n_cached)) and res.computed == [n_cached, n_cached + 1]
    fresh = runner.submit(make_flight(tmp_path / "g", seed=2), StepConfig(steps=n_cached + 2, units=2, iters=150),
                          processor=STEP).result(120)
    np.testing.assert_allclose(res.state, fresh.state, rtol=1e-9, atol=1e-12)


def test_failing_job_reports_its_error(runner, tmp_path):
    flight = make_flight(tmp_path / "f", seed=3)
    job = runner.submit(flight, StepConfig(steps=3, fail_at_step=1), processor=STEP)
    with pytest.raises(StepFailure, match="step 1 cannot read f/input.npy: bad values") as ei:
        job.result(timeout=120)
    assert job.status is JobStatus.FAILED
    assert any("raised in the job's worker" in n for n in getattr(ei.value, "__notes__", []))
    assert step_path(flight, 0).exists() and not step_path(flight, 1).exists()
    # an error that cannot cross processes comes back as JobFailed naming it
    job = runner.submit(make_flight(tmp_path / "g", seed=3), StepConfig(steps=2, unpicklable_at_step=0),
                        processor=STEP)
    with pytest.raises(JobFailed, match="_Unpicklable: holds a lock"):
        job.result(timeout=120)
    # a worker that dies fails its job only
    job = runner.submit(make_flight(tmp_path / "h", seed=3), StepConfig(steps=2, crash_at_step=0), processor=STEP)
    with pytest.raises(JobFailed, match="exit code 3"):
        job.result(timeout=120)
    # an unknown processor is refused at submit
    from reconstruction.jobs import JobError

    with pytest.raises(JobError, match="unknown processor"):
        runner.submit(flight, None, processor="no-such-processor")
    with pytest.raises(JobError, match="does not exist"):
        runner.submit(tmp_path / "missing", None, processor=STEP)


def test_two_flights_in_parallel_and_a_third_queued(runner, tmp_path):
    cfg = StepConfig(steps=30, units=2, iters=100)
    jobs = [runner.submit(make_flight(tmp_path / f"f{i}", seed=10 + i), cfg, processor=STEP) for i in range(3)]
    # two workers: the first two run at the same time, the third waits for a free worker
    _wait_for(lambda: jobs[0].status is JobStatus.RUNNING and jobs[1].status is JobStatus.RUNNING,
              what="both flights running")
    assert jobs[2].status is JobStatus.QUEUED
    assert jobs[0].worker["pid"] != jobs[1].worker["pid"]
    # a queued job cancelled never starts
    assert jobs[2].cancel()
    assert jobs[2].status is JobStatus.CANCELLED and jobs[2].started_at is None
    for j in jobs[:2]:
        j.cancel()
    assert all(j.wait(60) for j in jobs)
    assert not (tmp_path / "f2" / CACHE).exists()


def test_parallel_units_in_processes(tmp_path):
    """unit_workers=2: a job's parallel_map units run in other processes and give the same result."""
    with LocalRunner(workers=1, threads_per_worker=1, unit_workers=2) as r:
        res = r.submit(make_flight(tmp_path / "f", seed=5), StepConfig(steps=1, units=3), processor=STEP).result(120)
    with LocalRunner(workers=1, threads_per_worker=1) as r:
        ref = r.submit(make_flight(tmp_path / "g", seed=5), StepConfig(steps=1, units=3), processor=STEP).result(120)
    np.testing.assert_allclose(res.state, ref.state, rtol=1e-9, atol=1e-12)
