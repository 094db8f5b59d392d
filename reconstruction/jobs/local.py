"""Jobs in worker processes on this machine: at most ``workers`` flights at once, each in its own spawned process
(a crash, a leak or a segfault ends that job only; memory goes back when it ends).

Progress events, log lines and the outcome come back through a multiprocessing queue, in order; ``cancel()`` sets
a multiprocessing event that the worker mirrors into the processor's ``threading.Event``; a worker that has not
stopped ``cancel_grace_s`` later is terminated (SIGTERM, then SIGKILL).
"""

from __future__ import annotations

import atexit
import collections
import logging
import multiprocessing
import os
import queue
import sys
import threading
import time
import weakref
from pathlib import Path
from typing import Any

from reconstruction.jobs.events import JobError, JobFailed, JobStatus
from reconstruction.jobs.job import Job, Runner, dispatch
from reconstruction.jobs.registry import processor_spec
from reconstruction.jobs.units import ProcessUnits

log = logging.getLogger(__name__)

__all__ = ["LocalRunner"]


class LocalRunner(Runner):
    """Worker processes on this machine (the default runner).

    workers: flights processed at once; threads_per_worker: the BLAS / OpenMP / torch threads of each worker
    (``OMP_NUM_THREADS`` etc.; default: this machine's CPUs shared among the workers -- oversubscribed BLAS threads
    spin and slow a loaded machine down by orders of magnitude); unit_workers: processes a job's :func:`~reconstruction.jobs.units.parallel_map`
    may use (1: its units run in the job's process); cancel_grace_s: seconds a cancelled worker has to stop by itself.
    """

    name = "local"

    def __init__(self, workers: int = 1, *, threads_per_worker: int | None = None, unit_workers: int = 1, cancel_grace_s: float = 30.0,
                 start_method: str = "spawn"):
        if workers < 1:
            raise JobError(f"LocalRunner needs at least one worker, not {workers}")
        self.workers = int(workers)
        self.unit_workers = max(1, int(unit_workers))
        self.threads_per_worker = int(threads_per_worker or max(1, (os.cpu_count() or 1) // self.workers))
        self.cancel_grace_s = float(cancel_grace_s)
        # spawn: safe from a threaded parent (the Qt app, Ray, torch); each worker imports what it needs
        self._ctx = multiprocessing.get_context(start_method)
        super().__init__()
        self._pending: collections.deque[tuple[Job, str]] = collections.deque()
        self._running: dict[str, tuple[Job, Any]] = {}
        self._closed = False
        # before multiprocessing's own exit handler joins the (non-daemonic: they may start unit processes) workers
        atexit.register(_close_at_exit, weakref.ref(self))

    def __repr__(self) -> str:
        return f"LocalRunner(workers={self.workers})"

    def submit(self, flight_dir: str | Path, config: Any = None, *, processor: Any = "process") -> Job:
        """Queue ``processor(flight_dir, config, progress, cancel)``; it starts when a worker is free."""
        spec = processor_spec(processor)
        flight_dir = Path(flight_dir).resolve()
        if not flight_dir.is_dir():
            raise JobError(f"flight folder {flight_dir} does not exist: pass the folder a recording or the demo wrote")
        job = Job(flight_dir, spec, config, self.name)
        with self._lock:
            if self._closed:
                raise JobError("this LocalRunner is closed; make a new one")
            self._jobs.append(job)
            self._pending.append((job, spec))
        job._set_canceller(lambda: self._cancel(job))
        self._dispatch()
        return job

    def close(self, *, cancel: bool = True, timeout: float | None = None) -> None:
        """Stop taking jobs; ``cancel``: cancel the queued and running ones; wait for the workers to end."""
        with self._lock:
            self._closed = True
            jobs = list(self._jobs)
        if cancel:
            for job in jobs:
                job.cancel()
        for job in jobs:
            job.wait(timeout)

    # ------------------------------------------------------------------ scheduling
    def _dispatch(self) -> None:
        dropped: list[Job] = []
        with self._lock:
            while self._pending and len(self._running) < self.workers:
                job, spec = self._pending.popleft()
                if job.cancel_requested:
                    dropped.append(job)
                    continue
                cancel_evt = self._ctx.Event()
                q = self._ctx.Queue()
                proc = self._ctx.Process(target=_child_main, name=f"skycap-job-{job.id}", daemon=False,
                                         args=(spec, str(job.flight_dir), job.config, q, cancel_evt,
                                               self.unit_workers, self.threads_per_worker))
                self._running[job.id] = (job, cancel_evt)
                threading.Thread(target=self._pump, args=(job, proc, q, cancel_evt), name=f"job-{job.id}",
                                 daemon=True).start()
        for job in dropped:  # outside the lock: its done callbacks may submit
            job._finish(JobStatus.CANCELLED, message="cancelled before it started")

    def _cancel(self, job: Job) -> None:
        with self._lock:
            queued = any(j is job for j, _ in self._pending)
            if queued:
                self._pending = collections.deque((j, s) for j, s in self._pending if j is not job)
            running = self._running.get(job.id)
        if queued:
            job._finish(JobStatus.CANCELLED, message="cancelled before it started")
        elif running is not None:
            running[1].set()

    def _pump(self, job: Job, proc, q, cancel_evt) -> None:
        try:
            proc.start()
            ended = False
            cancel_seen: float | None = None
            while not ended:
                try:
                    msg = q.get(timeout=0.2)
                except queue.Empty:
                    if cancel_evt.is_set():
                        cancel_seen = cancel_seen or time.monotonic()
                        if time.monotonic() - cancel_seen > self.cancel_grace_s and proc.is_alive():
                            log.warning("job %s: the worker did not stop %.0f s after cancel; terminating it",
                                        job.id, self.cancel_grace_s)
                            _stop(proc)
                            job._finish(JobStatus.CANCELLED, message="worker terminated after the cancel grace time")
                            return
                    if not proc.is_alive():
                        # it may have put its last messages just before it exited
                        try:
                            while not ended:
                                ended = dispatch(job, q.get(timeout=0.5))
                        except queue.Empty:
                            pass
                        if not ended:
                            if cancel_evt.is_set():
                                job._finish(JobStatus.CANCELLED, message=f"worker exited with code {proc.exitcode}")
                            else:
                                job._finish(JobStatus.FAILED, error=JobFailed(
                                    f"the worker process of job {job.id} ended with exit code {proc.exitcode} without "
                                    f"a result (killed, out of memory or crashed); its log: {' | '.join(job.log[-5:])}"))
                            ended = True
                    continue
                ended = dispatch(job, msg)
            proc.join(timeout=10)
            if proc.is_alive():
                _stop(proc)
        except BaseException as e:  # noqa: BLE001 - the job must end whatever happened here
            log.exception("job %s: runner error", job.id)
            job._finish(JobStatus.FAILED, error=JobFailed(f"local runner error: {type(e).__name__}: {e}"))
            if proc.is_alive():
                _stop(proc)
        finally:
            with self._lock:
                self._running.pop(job.id, None)
            q.close()
            self._dispatch()


def _close_at_exit(ref) -> None:
    runner = ref()
    if runner is not None:
        runner.close(cancel=True, timeout=runner.cancel_grace_s + 10)


def _stop(proc) -> None:
    proc.terminate()
    proc.join(5)
    if proc.is_alive():
        proc.kill()
        proc.join(5)


_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def _limit_threads(n: int) -> None:
    """The worker's (and its unit processes') numeric libraries to ``n`` threads: read at their import, so set before
    numpy / torch are imported here; when they already are, through threadpoolctl where it is installed."""
    for var in _THREAD_VARS:
        os.environ[var] = str(n)
    if "numpy" in sys.modules:
        try:
            from threadpoolctl import threadpool_limits

            threadpool_limits(n)
        except ImportError:
            log.warning("numpy was imported before the worker could limit its threads to %d", n)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(n)


def _child_main(spec: str, flight_dir: str, cfg: Any, q, cancel_evt, unit_workers: int, threads: int) -> None:
    """The worker process: mirror the cancel event into a threading.Event, run the job, send back every message."""
    _limit_threads(threads)
    from reconstruction.jobs._worker import execute
    from skycap.childproc import die_with_parent

    try:
        # its own session, as Ray's workers and the ground station's subprocess jobs are: with the kernel's
        # autogroup scheduling a session is one scheduling group (each worker then gets a group's CPU share)
        os.setsid()
    except OSError:
        pass
    try:
        die_with_parent()
    except Exception:  # noqa: BLE001 - best effort (not Linux)
        pass
    cancel = threading.Event()

    def mirror() -> None:
        cancel_evt.wait()
        cancel.set()

    threading.Thread(target=mirror, daemon=True, name="cancel-mirror").start()
    execute(spec, flight_dir, cfg, q.put, cancel, ProcessUnits(unit_workers))
    q.close()
    q.join_thread()
