"""The Ray runner on a one-machine Ray cluster started by the tests on 127.0.0.1: the same results as the local
runner, progress events in order, cancel by ray.cancel leaving the cache consistent, errors passed through."""

from __future__ import annotations

import shutil
import threading
import time

import numpy as np
import pytest

from reconstruction.jobs import JobCancelled, JobStatus
from tests.reconstruction.jobs.stepjob import (CACHE, StepConfig, StepFailure, make_flight, step_job, step_path)
from tests.reconstruction.jobs.smallflight import QUICK

STEP = "tests.reconstruction.jobs.stepjob:step_job"


def test_ray_job_gives_the_local_result_with_units_as_ray_tasks(ray_runner, tmp_path):
    cfg = StepConfig(steps=3, units=3)
    job = ray_runner.submit(make_flight(tmp_path / "r", seed=7), cfg, processor=STEP)
    res = job.result(timeout=120)
    assert job.status is JobStatus.DONE and job.runner_name == "ray"
    expected = [(f"step{k}", f) for k in range(3) for f in (0.0, 1 / 3, 2 / 3, 1.0)]
    assert [(e.step, round(e.fraction, 6)) for e in job.events] == [(s, round(f, 6)) for s, f in expected]
    ref = step_job(make_flight(tmp_path / "l", seed=7), cfg, lambda e: None, threading.Event())  # as a local worker does
    np.testing.assert_allclose(res.state, ref.state, rtol=1e-9, atol=1e-12)
    assert res.computed == ref.computed == [0, 1, 2]


def test_ray_cancel_stops_the_job_and_leaves_the_cache_consistent(ray_runner, tmp_path):
    flight = make_flight(tmp_path / "f", seed=8)
    job = ray_runner.submit(flight, StepConfig(steps=60, units=1, iters=300), processor=STEP)
    t_end = time.monotonic() + 60
    while not any(e.step == "step1" for e in job.events):
        assert time.monotonic() < t_end and not job.done(), "step 1 never started"
        time.sleep(0.05)
    assert job.status is JobStatus.RUNNING
    job.cancel()  # ray.cancel of the task
    assert job.wait(60)
    assert job.status is JobStatus.CANCELLED
    with pytest.raises(JobCancelled):
        job.result(0)
    files = sorted((flight / CACHE).iterdir())
    time.sleep(1.0)
    assert sorted((flight / CACHE).iterdir()) == files, "the processor kept running after cancel"
    n = len(files)
    assert 1 <= n < 60 and files == [step_path(flight, k) for k in range(n)]
    # resumes from the cache, same state as an uninterrupted run here
    res = ray_runner.submit(flight, StepConfig(steps=n + 1, units=1, iters=300), processor=STEP).result(120)
    assert res.cached == list(range(n)) and res.computed == [n]
    ref = step_job(make_flight(tmp_path / "g", seed=8), StepConfig(steps=n + 1, units=1, iters=300), lambda e: None,
                   threading.Event())
    np.testing.assert_allclose(res.state, ref.state, rtol=1e-9, atol=1e-12)


def test_ray_job_error_passes_through(ray_runner, tmp_path):
    job = ray_runner.submit(make_flight(tmp_path / "f", seed=9), StepConfig(steps=2, fail_at_step=0), processor=STEP)
    with pytest.raises(StepFailure, match="step 0 cannot read f/input.npy"):
        job.result(timeout=120)
    assert job.status is JobStatus.FAILED


@pytest.mark.slow  # torch and the body model imported in a worker, a short fit
def test_reconstruct_flight_on_ray_equals_local(ray_runner, small_flight, local_reconstruction, tmp_path):
    a = shutil.copytree(small_flight, tmp_path / "ray")
    res = ray_runner.submit(a, QUICK, processor="reconstruct").result(timeout=300)
    local_job, b = local_reconstruction
    ref = local_job.result(timeout=0)
    np.testing.assert_allclose(res.joints_ned, ref.joints_ned, atol=1e-6)
    np.testing.assert_array_equal(res.t_ns, ref.t_ns)
    assert (a / "reconstruction" / "motion.bvh").read_text() == (b / "reconstruction" / "motion.bvh").read_text()


def test_ray_submit_refuses_a_missing_flight_folder(ray_runner, tmp_path):
    from reconstruction.jobs import JobError

    before = len(ray_runner.jobs)
    with pytest.raises(JobError, match=r"flight folder .*nowhere does not exist: pass the folder"):
        ray_runner.submit(tmp_path / "nowhere", StepConfig(steps=1), processor=STEP)
    assert len(ray_runner.jobs) == before  # nothing submitted
