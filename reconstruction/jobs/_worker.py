"""The body of a job where it runs (a local worker process or a Ray worker): resolve the processor, run it with
progress and cancel, and send back what happened as messages.

Messages (tuples, in order): ("started", {"pid", "host"}), ("event", ProgressEvent)*, ("log", line)*, then one of
("done", pickled result), ("failed", error payload), ("cancelled", message).
"""

from __future__ import annotations

import logging
import os
import pickle
import socket
import threading
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from reconstruction.jobs.events import JobFailed, ProgressEvent
from reconstruction.jobs.registry import resolve_processor
from reconstruction.jobs.units import SerialUnits, UnitExecutor, unit_context

Emit = Callable[[tuple], None]
TERMINAL_MESSAGES = frozenset({"done", "failed", "cancelled"})

_LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


class _EmitLog(logging.Handler):
    def __init__(self, emit: Emit):
        super().__init__(logging.INFO)
        self.setFormatter(logging.Formatter(_LOG_FORMAT))
        self._emit = emit

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self._emit(("log", self.format(record)))
        except Exception:  # noqa: BLE001 - a log line must never break the job
            pass


def execute(spec: str, flight_dir: str, cfg: Any, emit: Emit, cancel: threading.Event,
            units: UnitExecutor | None = None) -> None:
    """Run processor ``spec`` on ``flight_dir`` with ``cfg``; every outcome is a message (this never raises)."""
    t0 = time.monotonic()
    root = logging.getLogger()
    handler = _EmitLog(emit)
    level = root.level
    root.addHandler(handler)
    if root.level == logging.NOTSET or root.level > logging.INFO:
        root.setLevel(logging.INFO)
    try:
        emit(("started", {"pid": os.getpid(), "host": socket.gethostname()}))

        def progress(ev: Any) -> None:
            emit(("event", ProgressEvent.from_any(ev, time.monotonic() - t0)))

        try:
            fn = resolve_processor(spec)
            with unit_context(units or SerialUnits(), cancel):
                result = fn(Path(flight_dir), cfg, progress=progress, cancel=cancel)
            payload = pickle.dumps(result)
        except BaseException as e:  # noqa: BLE001 - every outcome goes back to the submitter
            if cancel.is_set():
                emit(("cancelled", f"{type(e).__name__}: {e}"))
            else:
                emit(("failed", error_payload(e)))
            if not isinstance(e, Exception):
                raise
            return
        emit(("done", payload))
    finally:
        root.removeHandler(handler)
        root.setLevel(level)


def error_payload(e: BaseException) -> dict[str, Any]:
    """An exception as data that crosses processes: its type, message, traceback and (when it round-trips through
    pickle) the exception itself."""
    pickled = None
    try:
        data = pickle.dumps(e)
        pickle.loads(data)
        pickled = data
    except Exception:  # noqa: BLE001 - re-raised as JobFailed with its type and message instead
        pass
    return {"type": f"{type(e).__module__}.{type(e).__qualname__}", "message": str(e),
            "traceback": "".join(traceback.format_exception(e)), "pickled": pickled}


def rebuild_error(payload: dict[str, Any]) -> BaseException:
    """The job's exception (its own type when it pickles, else :class:`JobFailed` naming it), with the worker's
    traceback attached as a note."""
    if payload.get("pickled") is not None:
        try:
            exc = pickle.loads(payload["pickled"])
            if isinstance(exc, BaseException):
                exc.add_note(f"raised in the job's worker:\n{payload.get('traceback', '')}")
                return exc
        except Exception:  # noqa: BLE001 - fall back to the text
            pass
    return JobFailed(f"{payload.get('type', 'error')}: {payload.get('message', '')}", payload.get("traceback", ""))
