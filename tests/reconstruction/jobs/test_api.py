"""The job API's pure parts, without worker processes: events, processors by name/path, the Job's bookkeeping,
the config and its command-line options."""

from __future__ import annotations

import argparse
import math
import pickle
import threading

import pytest

from reconstruction.jobs import (JobCancelled, JobError, JobsConfig, JobStatus, LocalRunner, ProgressEvent,
                                 add_job_args, jobs_config_from_args, register_processor, resolve_processor,
                                 runner_from_config)
from reconstruction.jobs._worker import error_payload, rebuild_error
from reconstruction.jobs.job import Job, dispatch
from reconstruction.jobs.registry import processor_spec
from reconstruction.jobs.units import SerialUnits, parallel_map, unit_context
from skycap.config import load_config
from tests.reconstruction.jobs.stepjob import StepEvent, StepFailure, step_job, unit


def test_progress_event_from_the_processors_own_class():
    ev = ProgressEvent.from_any(StepEvent("fit", 1.7, math.inf, "x"), elapsed_s=2.5)
    assert ev == ProgressEvent("fit", 1.0, None, "x", 2.5)
    assert ProgressEvent.from_any(StepEvent("fit", float("nan"), 3, ""), 0).fraction == 0.0
    with pytest.raises(JobError, match="must have .step and .fraction"):
        ProgressEvent.from_any(("fit", 0.5), 0)


def test_processors_by_name_path_or_function():
    path = "tests.reconstruction.jobs.stepjob:step_job"
    assert processor_spec(path) == path and resolve_processor(path) is step_job
    assert processor_spec(step_job) == path
    assert processor_spec("reconstruct") == "reconstruction.jobs.adapters:reconstruct_job"
    register_processor("steps-for-test", step_job)
    assert processor_spec("steps-for-test") == path
    with pytest.raises(JobError, match="cannot be imported by a worker"):
        processor_spec(lambda f, c, p, x: None)
    with pytest.raises(JobError, match="unknown processor 'nope'"):
        processor_spec("nope")
    with pytest.raises(JobError, match="module 'no_such_module' cannot be imported"):
        resolve_processor("no_such_module:fn")
    with pytest.raises(JobError, match="has no 'missing'"):
        resolve_processor("tests.reconstruction.jobs.stepjob:missing")


def test_job_bookkeeping_from_worker_messages(tmp_path):
    job = Job(tmp_path, "x:y", None, "test")
    got, done = [], []
    job.subscribe(got.append)
    job.add_done_callback(done.append)
    assert job.status is JobStatus.QUEUED and job.progress is None and job.elapsed_s == 0.0
    with pytest.raises(TimeoutError):
        job.result(timeout=0.01)
    evs = [ProgressEvent("a", 0.5), ProgressEvent("a", 1.0), ProgressEvent("b", 0.2)]
    it = job.iter_events(timeout=5)
    assert not dispatch(job, ("started", {"pid": 1}))
    assert job.status is JobStatus.RUNNING and job.worker == {"pid": 1}
    for ev in evs[:2]:
        dispatch(job, ("event", ev))
    assert next(it) == evs[0]
    late = []
    job.subscribe(late.append)  # replays the events so far
    dispatch(job, ("event", evs[2]))
    dispatch(job, ("log", "a line"))
    assert dispatch(job, ("done", pickle.dumps({"x": 1})))
    assert list(it) == evs[1:] and got == evs and late == evs and job.log == ["a line"]
    assert done == [job] and job.result() == {"x": 1} and job.progress == evs[-1]
    assert job.cancel() is False


def test_failed_and_cancelled_outcomes(tmp_path):
    job = Job(tmp_path, "x:y", None, "test")
    try:
        raise StepFailure("bad values")
    except StepFailure as e:
        payload = error_payload(e)
    dispatch(job, ("failed", payload))
    with pytest.raises(StepFailure, match="bad values"):
        job.result()
    assert job.status is JobStatus.FAILED and "bad values" in job.message
    exc = rebuild_error({**payload, "pickled": None})
    assert "StepFailure: bad values" in str(exc) and "Traceback" in exc.traceback
    job = Job(tmp_path, "x:y", None, "test")
    called = []
    job._set_canceller(lambda: called.append(1))
    assert job.cancel() and job.cancel_requested and called == [1]
    dispatch(job, ("cancelled", "StepCancelled: cancelled before step 3"))
    with pytest.raises(JobCancelled, match="cancelled before step 3"):
        job.result()


def test_parallel_map_serial_outside_a_job_and_cancel_inside():
    import numpy as np

    items = [(np.eye(4), 0, u, 4, 2) for u in range(3)]
    order = []
    out = parallel_map(unit, items, on_done=lambda i, r: order.append(i))
    assert len(out) == 3 and order == [0, 1, 2]
    cancel = threading.Event()
    cancel.set()
    with unit_context(SerialUnits(), cancel), pytest.raises(JobCancelled, match="after 0 of 3 units"):
        parallel_map(unit, items)


def test_jobs_config_toml_cli_and_runner(tmp_path):
    p = tmp_path / "jobs.toml"
    p.write_text('runner = "local"\nworkers = 2\nprocessor = "process"\n')
    cfg = load_config(JobsConfig, p, ["threads_per_worker=1"])
    assert (cfg.workers, cfg.processor, cfg.threads_per_worker) == (2, "process", 1)
    ap = argparse.ArgumentParser()
    add_job_args(ap)
    assert jobs_config_from_args(ap.parse_args([]), cfg) == cfg
    ray_cfg = jobs_config_from_args(ap.parse_args(["--ray", "10.0.0.5:6379"]), cfg)
    assert (ray_cfg.runner, ray_cfg.ray_address) == ("ray", "10.0.0.5:6379")
    assert jobs_config_from_args(ap.parse_args(["--workers", "3"]), cfg).workers == 3
    with pytest.raises(JobError, match="jobs.runner must be one of local, ray"):
        JobsConfig(runner="slurm")
    runner = runner_from_config(cfg)
    assert isinstance(runner, LocalRunner) and runner.workers == 2 and runner.threads_per_worker == 1
    runner.close()
