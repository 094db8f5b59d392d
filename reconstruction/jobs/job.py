"""A submitted job as its submitter sees it: status, progress events, log, cancel, result (thread-safe; no Qt).

Runners (:mod:`reconstruction.jobs.local`, :mod:`reconstruction.jobs.ray_runner`) feed it from one thread per job,
so events reach subscribers in the order the processor reported them.
"""

from __future__ import annotations

import abc
import logging
import pickle
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from reconstruction.jobs.events import JobCancelled, JobStatus, ProgressEvent, TERMINAL_STATES

log = logging.getLogger(__name__)

__all__ = ["Job", "Runner"]

_NO_RESULT = object()


class Job:
    """One flight being processed.

        job = runner.submit("flights/f1", cfg)
        job.status            # JobStatus.QUEUED / RUNNING / DONE / FAILED / CANCELLED (a str enum)
        job.progress          # the latest ProgressEvent (None before the first)
        unsubscribe = job.subscribe(print)        # every event, the ones so far first, then as they come
        for ev in job.iter_events(): ...          # the same as an iterator, ends when the job ends
        job.cancel()
        job.result(timeout=60)                    # the processor's result; raises its error, JobCancelled, TimeoutError
    """

    def __init__(self, flight_dir: Path, processor: str, config: Any, runner_name: str):
        self.id = uuid.uuid4().hex[:12]
        self.flight_dir = Path(flight_dir)
        self.processor = processor
        self.config = config
        self.runner_name = runner_name
        self.submitted_at = time.time()
        self.started_at: float | None = None
        self.finished_at: float | None = None
        self.worker: dict[str, Any] = {}
        self._cond = threading.Condition()
        self._status = JobStatus.QUEUED
        self._events: list[ProgressEvent] = []
        self._log: list[str] = []
        self._subscribers: list[Callable[[ProgressEvent], None]] = []
        self._done_callbacks: list[Callable[[Job], None]] = []
        self._result_bytes: Any = _NO_RESULT
        self._result: Any = _NO_RESULT
        self._error: BaseException | None = None
        self._message = ""
        self._cancel_requested = False
        self._canceller: Callable[[], None] | None = None

    def __repr__(self) -> str:
        return f"<Job {self.id} {self.flight_dir.name} {self.status} on {self.runner_name}>"

    # ------------------------------------------------------------------ what the submitter reads
    @property
    def status(self) -> JobStatus:
        with self._cond:
            return self._status

    @property
    def progress(self) -> ProgressEvent | None:
        """The latest progress event (None before the first)."""
        with self._cond:
            return self._events[-1] if self._events else None

    @property
    def events(self) -> list[ProgressEvent]:
        """Every progress event so far, in order."""
        with self._cond:
            return list(self._events)

    @property
    def log(self) -> list[str]:
        """The worker's log lines (INFO and above) so far."""
        with self._cond:
            return list(self._log)

    @property
    def message(self) -> str:
        """Why it failed or was cancelled ("" otherwise)."""
        with self._cond:
            return self._message

    @property
    def cancel_requested(self) -> bool:
        with self._cond:
            return self._cancel_requested

    @property
    def elapsed_s(self) -> float:
        """Seconds since it started running (0 while queued; frozen once finished)."""
        with self._cond:
            if self.started_at is None:
                return 0.0
            return (self.finished_at or time.time()) - self.started_at

    def done(self) -> bool:
        return self.status in TERMINAL_STATES

    def subscribe(self, callback: Callable[[ProgressEvent], None], *, replay: bool = True) -> Callable[[], None]:
        """Call ``callback(event)`` for every progress event (``replay``: first the events so far), from the runner's
        thread (a GUI posts it to its own thread). Returns the function that unsubscribes."""
        with self._cond:
            past = list(self._events) if replay else []
            self._subscribers.append(callback)
        for ev in past:
            _call(callback, ev)

        def unsubscribe() -> None:
            with self._cond:
                if callback in self._subscribers:
                    self._subscribers.remove(callback)

        return unsubscribe

    def add_done_callback(self, callback: Callable[["Job"], None]) -> None:
        """Call ``callback(job)`` once the job has ended (at once when it already has)."""
        with self._cond:
            if self._status not in TERMINAL_STATES:
                self._done_callbacks.append(callback)
                return
        _call(callback, self)

    def iter_events(self, timeout: float | None = None) -> Iterator[ProgressEvent]:
        """The progress events in order, from the first, waiting for new ones until the job ends (``timeout``: at most
        that many seconds in all, then :class:`TimeoutError`)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        i = 0
        while True:
            with self._cond:
                while i >= len(self._events) and self._status not in TERMINAL_STATES:
                    left = None if deadline is None else deadline - time.monotonic()
                    if left is not None and left <= 0:
                        raise TimeoutError(f"job {self.id} still {self._status} after {timeout} s")
                    self._cond.wait(left)
                batch = self._events[i:]
                ended = self._status in TERMINAL_STATES
            i += len(batch)
            yield from batch
            if ended and not batch:
                return

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the job ends; False when ``timeout`` passed first."""
        with self._cond:
            return self._cond.wait_for(lambda: self._status in TERMINAL_STATES, timeout)

    def result(self, timeout: float | None = None) -> Any:
        """The processor's result once done. Raises the job's own error (with the worker's traceback as a note; a
        :class:`JobFailed` naming its type when it cannot be rebuilt here), :class:`JobCancelled`, or
        :class:`TimeoutError` when it is not done within ``timeout`` seconds."""
        if not self.wait(timeout):
            raise TimeoutError(f"job {self.id} ({self.flight_dir}) still {self.status} after {timeout} s")
        with self._cond:
            if self._status is JobStatus.CANCELLED:
                raise JobCancelled(f"job {self.id} ({self.flight_dir}) was cancelled: {self._message}")
            if self._status is JobStatus.FAILED:
                assert self._error is not None
                raise self._error
            if self._result is _NO_RESULT:
                self._result = pickle.loads(self._result_bytes)
            return self._result

    def cancel(self) -> bool:
        """Ask the job to stop: a queued job never starts; a running one gets its cancel event set (the processor
        stops at its next check, leaving its cache consistent). False when it had already ended."""
        with self._cond:
            if self._status in TERMINAL_STATES:
                return False
            first = not self._cancel_requested
            self._cancel_requested = True
            canceller = self._canceller
        if first:
            log.info("cancelling job %s (%s)", self.id, self.flight_dir)
        if canceller is not None:
            canceller()
        return True

    # ------------------------------------------------------------------ what the runner calls
    def _set_canceller(self, canceller: Callable[[], None]) -> None:
        with self._cond:
            self._canceller = canceller

    def _set_running(self, worker: dict[str, Any]) -> None:
        with self._cond:
            if self._status is JobStatus.QUEUED:
                self._status = JobStatus.RUNNING
                self.started_at = time.time()
                self.worker = dict(worker)
                self._cond.notify_all()

    def _add_event(self, ev: ProgressEvent) -> None:
        with self._cond:
            self._events.append(ev)
            subs = list(self._subscribers)
            self._cond.notify_all()
        for cb in subs:
            _call(cb, ev)

    def _add_log(self, line: str) -> None:
        with self._cond:
            self._log.append(line)

    def _finish(self, status: JobStatus, *, result_bytes: bytes | None = None, error: BaseException | None = None,
                message: str = "") -> None:
        assert status in TERMINAL_STATES
        with self._cond:
            if self._status in TERMINAL_STATES:
                return
            self._status = status
            if self.started_at is None and status is not JobStatus.CANCELLED:
                self.started_at = time.time()
            self.finished_at = time.time()
            self._result_bytes = result_bytes
            self._error = error
            self._message = message or (str(error) if error is not None else "")
            callbacks, self._done_callbacks = self._done_callbacks, []
            self._cond.notify_all()
        log.info("job %s (%s) %s%s", self.id, self.flight_dir, status, f": {self._message}" if self._message else "")
        for cb in callbacks:
            _call(cb, self)


def _call(cb: Callable, arg: Any) -> None:
    try:
        cb(arg)
    except Exception:  # noqa: BLE001 - a subscriber's bug must not stop the job's bookkeeping
        log.exception("job callback %r failed", cb)


class Runner(abc.ABC):
    """What every runner shares: the jobs it was given (``jobs``, guarded by ``_lock``) and use as a context
    manager (``with LocalRunner() as r:`` closes it, cancelling what still runs). Subclasses define ``name``,
    ``submit`` and ``close``."""

    name = ""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._jobs: list[Job] = []

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @abc.abstractmethod
    def submit(self, flight_dir: str | Path, config: Any = None, *, processor: Any = "process") -> Job:
        """Start processing ``flight_dir`` with ``config``; the :class:`Job` to follow it."""

    @abc.abstractmethod
    def close(self, *, cancel: bool = True, timeout: float | None = None) -> None:
        """Stop taking jobs; cancel the running ones (``cancel``) and wait up to ``timeout`` s for them."""

    @property
    def jobs(self) -> list[Job]:
        with self._lock:
            return list(self._jobs)


def dispatch(job: Job, msg: tuple) -> bool:
    """Apply one worker message to ``job``; True when it was the last one (the job has ended)."""
    from reconstruction.jobs._worker import rebuild_error

    kind = msg[0]
    if kind == "started":
        job._set_running(msg[1])
    elif kind == "event":
        job._add_event(msg[1])
    elif kind == "log":
        job._add_log(msg[1])
    elif kind == "done":
        job._finish(JobStatus.DONE, result_bytes=msg[1])
        return True
    elif kind == "failed":
        job._finish(JobStatus.FAILED, error=rebuild_error(msg[1]))
        return True
    elif kind == "cancelled":
        job._finish(JobStatus.CANCELLED, message=msg[1])
        return True
    else:
        log.warning("job %s: unknown worker message %r", job.id, kind)
    return False
