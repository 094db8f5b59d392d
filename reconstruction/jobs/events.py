"""What a job reports and how it ends: progress events, states, errors (no runner, no I/O)."""

from __future__ import annotations

import dataclasses
import enum
import math
from typing import Any

from skycap.errors import SkycapError

__all__ = ["JobCancelled", "JobError", "JobFailed", "JobStatus", "ProgressEvent", "TERMINAL_STATES"]


class JobStatus(str, enum.Enum):
    """Where a job is: ``queued`` -> ``running`` -> ``done`` / ``failed`` / ``cancelled`` (a queued job can be
    cancelled before it runs)."""

    QUEUED = "queued"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"

    def __str__(self) -> str:  # "running", not "JobStatus.RUNNING", in logs and UIs
        return self.value


TERMINAL_STATES = frozenset({JobStatus.DONE, JobStatus.FAILED, JobStatus.CANCELLED})


class JobError(SkycapError):
    """A job that cannot be submitted or run as asked (unknown processor, runner not available, ...)."""


class JobFailed(JobError):
    """The job's processing raised an error that could not be re-raised as its own type; the message carries the
    original type and message, :attr:`traceback` the worker's traceback."""

    def __init__(self, message: str, traceback: str = ""):
        super().__init__(message)
        self.traceback = traceback


class JobCancelled(JobError):
    """The job was cancelled (``Job.cancel()``) before it finished: there is no result."""


@dataclasses.dataclass(frozen=True)
class ProgressEvent:
    """One progress report of a processing step.

    step: the step's name ("keypoints", "fit", ...); fraction: 0..1 of that step; eta_s: the processor's estimate of
    the seconds left (None: unknown); message: free text for a log or status line. elapsed_s: seconds since the job
    started running, stamped by the runner where the event was made (the worker).
    """

    step: str
    fraction: float
    eta_s: float | None = None
    message: str = ""
    elapsed_s: float = 0.0

    @classmethod
    def from_any(cls, ev: Any, elapsed_s: float) -> "ProgressEvent":
        """A processor's event (any object with ``step``, ``fraction``, ``eta_s``, ``message`` -- e.g. the processing
        function's own ProgressEvent class) as this runner-side, picklable-everywhere event."""
        try:
            step, fraction = str(ev.step), float(ev.fraction)
        except AttributeError as e:
            raise JobError(f"a progress event must have .step and .fraction (and optionally .eta_s, .message); got "
                           f"{type(ev).__name__}: {ev!r}") from e
        eta = getattr(ev, "eta_s", None)
        eta = None if eta is None or not math.isfinite(float(eta)) else float(eta)
        fraction = min(1.0, max(0.0, fraction)) if math.isfinite(fraction) else 0.0
        return cls(step, fraction, eta, str(getattr(ev, "message", "") or ""), float(elapsed_s))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)
