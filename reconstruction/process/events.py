"""Progress events, cancellation and the errors of :func:`reconstruction.process.process`.

    def on_progress(ev: ProgressEvent) -> None:
        print(ev.step, f"{ev.fraction:.0%}", ev.eta_s, ev.message)

    cancel = threading.Event()          # set it from another thread: process() raises Cancelled at the next batch
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable

from skycap.errors import SkycapError

__all__ = ["STEPS", "Cancelled", "ProcessError", "ProgressEvent", "ProgressSink", "StepProgress"]

#: The steps of ``skycap process``, in order.
STEPS: tuple[str, ...] = ("boxes", "keypoints", "fit", "export")


class ProcessError(SkycapError):
    """A flight that cannot be processed as asked (too few readable drones, a bad setting)."""


class Cancelled(SkycapError):
    """Processing was cancelled (the ``cancel`` event was set). Finished steps, chunks and windows stay in the
    flight's ``processing/`` cache: running again resumes from there."""


@dataclasses.dataclass(frozen=True)
class ProgressEvent:
    """One progress report: ``step`` (one of :data:`STEPS`), ``fraction`` of that step done (0..1), ``eta_s`` the
    estimated seconds left in the step (None while unknown) and a human ``message`` (e.g. ``"drone_1: 64/300
    frames"``, ``"cached"``)."""

    step: str
    fraction: float
    eta_s: float | None
    message: str = ""


ProgressSink = Callable[[ProgressEvent], None]


class StepProgress:
    """Turns a step's ``done / total`` counts into :class:`ProgressEvent` s with an ETA (from the rate of the work
    done in this run; work found in the cache counts as done but not in the rate), and checks ``cancel``."""

    def __init__(self, step: str, sink: ProgressSink | None, cancel: threading.Event | None) -> None:
        self.step, self.sink, self.cancel = step, sink, cancel
        self.t0 = time.perf_counter()
        self.start_done = None

    def check_cancel(self) -> None:
        if self.cancel is not None and self.cancel.is_set():
            raise Cancelled(f"processing cancelled during the {self.step} step; run it again to resume from the cache")

    def __call__(self, done: float, total: float, message: str = "") -> None:
        frac = min(max(float(done) / total, 0.0), 1.0) if total > 0 else 1.0
        if self.start_done is None:
            self.start_done = frac
        eta = None
        dt = time.perf_counter() - self.t0
        if frac >= 1.0:
            eta = 0.0
        elif frac > self.start_done and dt > 0:
            eta = dt * (1.0 - frac) / (frac - self.start_done)
        if self.sink is not None:
            self.sink(ProgressEvent(self.step, frac, eta, message))
        self.check_cancel()
