"""Jobs on a Ray cluster: each flight a Ray task (``num_cpus_per_job`` CPUs), its
:func:`~reconstruction.jobs.units.parallel_map` units further Ray tasks spread over the cluster.

    runner = RayRunner("127.0.0.1:6379")     # or "auto" (the cluster this machine belongs to), "local" (start one here)
    job = runner.submit("flights/f1", cfg)   # same Job API as the local runner, same result

The job task is a streaming generator: it yields the processor's progress events, log lines and the outcome as they
happen, in order. ``Job.cancel()`` is ``ray.cancel`` of that task: Ray raises KeyboardInterrupt in the task, which
sets the processor's cancel event and waits for the processor to stop (its cache stays consistent).

The flight folder is read and written by path on the node that runs the task: on a cluster of several machines it
must be on storage every node sees at the same path, and skycap installed on every node (or shipped with
``runtime_env={"working_dir": ...}``). By default the workers get this checkout on their PYTHONPATH (what a
cluster on this machine needs).
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from pathlib import Path
from typing import Any

from reconstruction.jobs.events import JobCancelled, JobError, JobFailed, JobStatus
from reconstruction.jobs.job import Job, Runner, dispatch
from reconstruction.jobs.registry import processor_spec

log = logging.getLogger(__name__)

__all__ = ["RayRunner", "RayUnits"]

_CHECKOUT = Path(__file__).resolve().parents[2]


def _ray():
    try:
        import ray
    except ModuleNotFoundError as e:
        raise JobError("the Ray runner needs Ray: pip install 'skycap[ray]' (or pip install 'ray[default]'), or use "
                       "the local runner (leave out --ray)") from e
    return ray


class RayRunner(Runner):
    """Jobs as Ray tasks on the cluster at ``address`` (None/"auto": the running cluster this machine belongs to;
    "local": start a one-machine cluster in this process; "HOST:PORT": that head's GCS).

    When this process is already connected to Ray (``ray.init`` done), that connection is used as it is.
    num_cpus_per_job / unit_cpus: CPUs Ray reserves for a job task / for each of its units; runtime_env: Ray's (the
    default puts this checkout on the workers' PYTHONPATH); init_kwargs: more ``ray.init`` arguments.
    """

    name = "ray"

    def __init__(self, address: str | None = None, *, num_cpus_per_job: float = 1.0, unit_cpus: float = 1.0,
                 runtime_env: dict | None = None, **init_kwargs: Any):
        ray = _ray()
        self.num_cpus_per_job = float(num_cpus_per_job)
        self.unit_cpus = float(unit_cpus)
        super().__init__()
        self._owns = False
        if ray.is_initialized():
            log.info("Ray runner on the cluster this process is already connected to")
        else:
            if runtime_env is None:
                paths = [str(_CHECKOUT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
                runtime_env = {"env_vars": {"PYTHONPATH": os.pathsep.join(dict.fromkeys(paths))}}
            init_kwargs.setdefault("logging_level", logging.WARNING)
            init_kwargs.setdefault("log_to_driver", False)
            try:
                ray.init(address=address or "auto", runtime_env=runtime_env, **init_kwargs)
            except ConnectionError as e:
                if _auth_refused(e):
                    raise JobError(
                        f"the Ray cluster at {address!r} refused this connection: it requires token authentication "
                        "(Ray >= 2.52 turns it on for `ray start`) and Ray never sends a token to an address given "
                        "explicitly unless told to: set RAY_AUTH_MODE=token and the cluster's token (RAY_AUTH_TOKEN, "
                        "RAY_AUTH_TOKEN_PATH or ~/.ray/auth_token; `ray get-auth-token` on the head prints it)") from e
                raise JobError(f"no Ray cluster at {address or 'auto'!r} ({e}); start one (ray start --head) and pass its "
                               f"address HOST:PORT, or use the local runner") from e
            self._owns = True
        self.address = ray.get_runtime_context().gcs_address
        log.info("Ray runner: cluster %s, %s CPUs", self.address, ray.cluster_resources().get("CPU"))

    def __repr__(self) -> str:
        return f"RayRunner({self.address!r})"

    def submit(self, flight_dir: str | Path, config: Any = None, *, processor: Any = "process") -> Job:
        """Submit ``processor(flight_dir, config, progress, cancel)`` as a Ray task; it runs when the cluster has
        ``num_cpus_per_job`` CPUs free (queued until then). A ``flight_dir`` that is not a folder here is refused
        with :class:`JobError` (the local runner's check)."""
        ray = _ray()
        spec = processor_spec(processor)
        flight_dir = Path(flight_dir).resolve()
        if not flight_dir.is_dir():  # as the local runner: refused here, not as a failed task on a worker
            raise JobError(f"flight folder {flight_dir} does not exist: pass the folder a recording or the demo wrote "
                           "(on a cluster of several machines, a path on storage every node sees)")
        job = Job(flight_dir, spec, config, self.name)
        task = _job_task().options(num_cpus=self.num_cpus_per_job, num_returns="streaming", max_retries=0)
        gen = task.remote(spec, str(flight_dir), config, self.unit_cpus)
        job._set_canceller(lambda: ray.cancel(gen))
        with self._lock:
            self._jobs.append(job)
        threading.Thread(target=self._pump, args=(job, gen), name=f"ray-job-{job.id}", daemon=True).start()
        return job

    def close(self, *, cancel: bool = True, timeout: float | None = 60.0) -> None:
        """Cancel (``cancel``) and wait for this runner's jobs; disconnect when this runner connected."""
        for job in self.jobs:
            if cancel:
                job.cancel()
        for job in self.jobs:
            job.wait(timeout)
        if self._owns:
            _ray().shutdown()
            self._owns = False

    def _pump(self, job: Job, gen) -> None:
        ray = _ray()
        from ray.exceptions import RayError, TaskCancelledError

        try:
            for ref in gen:
                if dispatch(job, ray.get(ref)):
                    return
            job._finish(JobStatus.FAILED, error=JobFailed(f"the Ray task of job {job.id} ended without a result"))
        except (TaskCancelledError, RayError) as e:
            cancelled = isinstance(e, TaskCancelledError) or isinstance(getattr(e, "cause", None), TaskCancelledError)
            if cancelled or job.cancel_requested:
                job._finish(JobStatus.CANCELLED, message="cancelled (ray.cancel)")
            else:
                job._finish(JobStatus.FAILED, error=JobFailed(f"the Ray task of job {job.id} failed: {e}"))
        except BaseException as e:  # noqa: BLE001 - the job must end whatever happened here
            log.exception("job %s: Ray runner error", job.id)
            job._finish(JobStatus.FAILED, error=JobFailed(f"Ray runner error: {type(e).__name__}: {e}"))


def _auth_refused(e: BaseException) -> bool:
    """Whether a failed ``ray.init`` was the cluster refusing a missing or wrong authentication token."""
    seen = 0
    while e is not None and seen < 10:
        if type(e).__name__ == "AuthenticationError" or "InvalidAuthToken" in str(e):
            return True
        e, seen = e.__cause__ or e.__context__, seen + 1
    return False


class RayUnits:
    """:func:`~reconstruction.jobs.units.parallel_map` inside a Ray job: each unit a Ray task of ``unit_cpus`` CPUs."""

    def __init__(self, unit_cpus: float = 1.0):
        self.unit_cpus = unit_cpus

    def map(self, fn, items, cancel, on_done):
        ray = _ray()
        remote = _unit_task().options(num_cpus=self.unit_cpus, max_retries=0)
        refs = [remote.remote(fn, item) for item in items]
        index = {r: i for i, r in enumerate(refs)}
        out: list[Any] = [None] * len(items)
        pending = list(refs)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1, timeout=0.2)
            for r in ready:
                out[index[r]] = ray.get(r)
                if on_done is not None:
                    on_done(index[r], out[index[r]])
            if cancel.is_set() and pending:
                for r in pending:
                    ray.cancel(r)
                raise JobCancelled(f"cancelled with {len(pending)} of {len(items)} units not finished")
        return out


# ---------------------------------------------------------------------- the tasks (defined once Ray is imported)
_TASKS: dict[str, Any] = {}


def _job_task():
    if "job" not in _TASKS:
        _TASKS["job"] = _ray().remote(_job_body)
    return _TASKS["job"]


def _unit_task():
    if "unit" not in _TASKS:
        _TASKS["unit"] = _ray().remote(_unit_body)
    return _TASKS["unit"]


def _unit_body(fn, item):
    return fn(item)


def _job_body(spec: str, flight_dir: str, cfg: Any, unit_cpus: float):
    """The Ray task: the job in a thread of this worker, its messages yielded as they come; ray.cancel
    (KeyboardInterrupt here) sets the processor's cancel event and waits for it to stop."""
    from reconstruction.jobs._worker import TERMINAL_MESSAGES, execute

    q: queue.Queue = queue.Queue()
    cancel = threading.Event()
    t = threading.Thread(target=execute, args=(spec, flight_dir, cfg, q.put, cancel, RayUnits(unit_cpus)),
                         name="skycap-job", daemon=True)
    t.start()
    try:
        while True:
            try:
                msg = q.get(timeout=0.1)
            except queue.Empty:
                if not t.is_alive() and q.empty():
                    return
                continue
            yield msg
            if msg[0] in TERMINAL_MESSAGES:
                return
    except BaseException:
        cancel.set()
        t0 = time.monotonic()
        t.join()
        logging.getLogger(__name__).info("job on %s cancelled; the processor stopped %.1f s later", flight_dir,
                                         time.monotonic() - t0)
        raise
