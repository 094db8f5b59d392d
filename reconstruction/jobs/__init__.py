"""Processing jobs: a flight processed by a processing callable in a worker process or on a Ray cluster, with
status, progress events, cancel and result (a library; the ground station's Qt models wrap it).

    from reconstruction.jobs import submit, LocalRunner, RayRunner, JobsConfig, runner_from_config

    job = submit("flights/f1", cfg)                    # the default runner: worker processes on this machine
    job.subscribe(lambda ev: print(ev.step, ev.fraction, ev.eta_s))
    res = job.result(timeout=600)                      # raises the job's error / JobCancelled

    with RayRunner("127.0.0.1:6379") as ray_runner:    # the same API on a Ray cluster
        res = ray_runner.submit("flights/f1", cfg, processor="process").result()

A processor is ``fn(flight_dir, cfg, *, progress, cancel) -> result`` (progress and cancel passed by keyword) named by a registered name or import path
(:mod:`reconstruction.jobs.registry`); it may spread independent units over the runner with
:func:`reconstruction.jobs.units.parallel_map`.
"""

from __future__ import annotations

import atexit
import threading
from pathlib import Path
from typing import Any

from reconstruction.jobs.config import JobsConfig, add_job_args, jobs_config_from_args, runner_from_config
from reconstruction.jobs.events import JobCancelled, JobError, JobFailed, JobStatus, ProgressEvent
from reconstruction.jobs.job import Job
from reconstruction.jobs.local import LocalRunner
from reconstruction.jobs.registry import register_processor, registered_processors, resolve_processor
from reconstruction.jobs.units import parallel_map

__all__ = ["Job", "JobCancelled", "JobError", "JobFailed", "JobStatus", "JobsConfig", "LocalRunner", "ProgressEvent",
           "RayRunner", "add_job_args", "default_runner", "jobs_config_from_args", "parallel_map",
           "register_processor", "registered_processors", "resolve_processor", "runner_from_config", "submit"]

_default: list[Any] = []
_default_lock = threading.Lock()


def __getattr__(name: str):
    if name == "RayRunner":  # Ray is an optional extra: imported when asked for
        from reconstruction.jobs.ray_runner import RayRunner

        return RayRunner
    raise AttributeError(name)


def default_runner():
    """The process-wide runner :func:`submit` uses: a :class:`LocalRunner` with the default :class:`JobsConfig`
    (closed at exit)."""
    with _default_lock:
        if not _default:
            runner = runner_from_config(JobsConfig())
            atexit.register(runner.close)
            _default.append(runner)
        return _default[0]


def submit(flight_dir: str | Path, config: Any = None, *, processor: Any = None, runner: Any = None) -> Job:
    """Process ``flight_dir`` with ``processor`` (default: :attr:`JobsConfig.processor`) and ``config`` on ``runner``
    (default: :func:`default_runner`)."""
    runner = runner or default_runner()
    return runner.submit(flight_dir, config, processor=processor or JobsConfig().processor)
