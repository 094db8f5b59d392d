"""The hook through which a processor spreads its independent units (per drone, per window) over the runner.

    from reconstruction.jobs.units import parallel_map

    def process(flight_dir, cfg, progress, cancel):
        per_drone = parallel_map(keypoints_of_drone, [(flight_dir, d, cfg) for d in drones],
                                 on_done=lambda i, r: progress(ProgressEvent("keypoints", ...)))

``parallel_map(fn, items)`` returns ``[fn(item) for item in items]`` in item order. Outside a job, and in a local
job with ``unit_workers=1`` (the default: the local runner already runs one flight per worker process), it runs
in this thread; a local job with ``unit_workers=N`` runs the units in N spawned processes; a Ray job submits each
unit as a Ray task (spread over the cluster). ``fn`` must be a module-level function (workers import it) and
``items`` and the results picklable. When the job is cancelled, the units not started are dropped and
:class:`reconstruction.jobs.events.JobCancelled` is raised here.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import contextvars
import multiprocessing
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any, Protocol

from reconstruction.jobs.events import JobCancelled

__all__ = ["ProcessUnits", "SerialUnits", "UnitExecutor", "parallel_map", "unit_context"]

OnDone = Callable[[int, Any], None]


class UnitExecutor(Protocol):
    def map(self, fn: Callable[[Any], Any], items: Sequence[Any], cancel: threading.Event,
            on_done: OnDone | None) -> list[Any]: ...


class SerialUnits:
    """Units one after the other in this thread (cancel checked between units)."""

    def map(self, fn, items, cancel, on_done):
        out = []
        for i, item in enumerate(items):
            if cancel.is_set():
                raise JobCancelled(f"cancelled after {i} of {len(items)} units")
            out.append(fn(item))
            if on_done is not None:
                on_done(i, out[-1])
        return out


class ProcessUnits:
    """Units in ``workers`` spawned processes on this machine (a pool per call: units are coarse)."""

    def __init__(self, workers: int):
        self.workers = max(1, int(workers))

    def map(self, fn, items, cancel, on_done):
        if self.workers == 1 or len(items) <= 1:
            return SerialUnits().map(fn, items, cancel, on_done)
        out: list[Any] = [None] * len(items)
        ctx = multiprocessing.get_context("spawn")
        with cf.ProcessPoolExecutor(min(self.workers, len(items)), mp_context=ctx) as pool:
            futs = {pool.submit(fn, item): i for i, item in enumerate(items)}
            pending = set(futs)
            while pending:
                done, pending = cf.wait(pending, timeout=0.2, return_when=cf.FIRST_COMPLETED)
                for f in done:
                    out[futs[f]] = f.result()
                    if on_done is not None:
                        on_done(futs[f], out[futs[f]])
                if cancel.is_set() and pending:
                    for f in pending:
                        f.cancel()
                    raise JobCancelled(f"cancelled with {len(pending)} of {len(items)} units not finished")
        return out


_current: contextvars.ContextVar[tuple[UnitExecutor, threading.Event] | None] = contextvars.ContextVar(
    "skycap_job_units", default=None)


@contextlib.contextmanager
def unit_context(executor: UnitExecutor, cancel: threading.Event) -> Iterator[None]:
    """Within this block (in this thread), :func:`parallel_map` uses ``executor`` and honours ``cancel``."""
    token = _current.set((executor, cancel))
    try:
        yield
    finally:
        _current.reset(token)


def parallel_map(fn: Callable[[Any], Any], items: Iterable[Any], *, on_done: OnDone | None = None) -> list[Any]:
    """``[fn(item) for item in items]``, spread over the job's runner (see the module doc); ``on_done(i, result)``
    is called here, in this thread, as each unit finishes (in completion order)."""
    items = list(items)
    cur = _current.get()
    if cur is None:
        return SerialUnits().map(fn, items, threading.Event(), on_done)
    executor, cancel = cur
    return executor.map(fn, items, cancel, on_done)
