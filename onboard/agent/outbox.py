"""The agent's way out: its Zenoh keys, publishing on the bus and recording to its MCAP file.

Everything the agent sends or receives is recorded on the recorder channel of its key (``state``,
``gcs/cmd`` ...; :func:`flightdata.recorder.channel_name`). A dead network or a failing recorder never stops
the flight: publishing failures are logged; a recording failure is logged, reported (``on_record_failure``:
the agent's health warnings) and, with ``reopen_recorder``, a new recording (the next sortie file) is opened in
its place, at most every ``reopen_interval_s`` (a disk that stays full: retried as often, reported once).

:meth:`Outbox.recorder_status` is what the agent's health says of the recording (:class:`shared_msgs.RecorderStatus`):
the current recorder's file and counters, the last failure, and the free space of the recording folder -- taken
with ``shutil.disk_usage`` on a background thread at most every ``disk_check_interval_s`` (a slow or hung file
system never holds up the agent's loop: the last value is reported meanwhile).
"""

from __future__ import annotations

import logging
import shutil
import threading
import time
from pathlib import Path
from typing import Any, Callable

from flightdata.recorder import channel_name
from shared_msgs import Message, RecorderStatus, encode, keys, stamp_sent

log = logging.getLogger(__name__)

__all__ = ["DiskFree", "Outbox"]


class DiskFree:
    """Free bytes of a folder's file system, measured on a background thread at most every ``interval_s``.

    :meth:`get` never blocks: it returns the last measurement (-1 before the first one, or after a failure:
    ``error`` says why) and starts a new one when the last is older than ``interval_s``."""

    def __init__(self, interval_s: float = 5.0, disk_usage: Callable[[str], Any] = shutil.disk_usage,
                 clock: Callable[[], float] = time.monotonic):
        self.interval_s = interval_s
        self._disk_usage = disk_usage
        self._clock = clock
        self.free_bytes = -1
        self.error = ""
        self._path: str | None = None
        self._t_started_s = -float("inf")
        self._thread: threading.Thread | None = None

    def get(self, path: str | Path) -> int:
        path = str(path)
        now = self._clock()
        busy = self._thread is not None and self._thread.is_alive()
        if not busy and (path != self._path or now - self._t_started_s >= self.interval_s):
            if path != self._path:
                self.free_bytes, self.error = -1, ""  # another folder: the old value says nothing of it
            self._path, self._t_started_s = path, now
            self._thread = threading.Thread(target=self._measure, args=(path,), name="disk-free", daemon=True)
            self._thread.start()
        return self.free_bytes

    def wait(self, timeout_s: float = 5.0) -> None:
        """Wait for the measurement in progress (tests)."""
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _measure(self, path: str) -> None:
        t0 = time.perf_counter()
        try:
            free = int(self._disk_usage(path).free)
        except Exception as e:
            if self.error != str(e):
                log.warning("free disk space of %s unknown: %s", path, e)
            self.free_bytes, self.error = -1, f"free space of {path} unknown: {e}"
            return
        dt = time.perf_counter() - t0
        if dt > 0.5:
            log.warning("measuring the free space of %s took %.1f s (slow file system)", path, dt)
        if path == self._path:
            self.free_bytes, self.error = free, ""


class Outbox:
    """Publishing and recording for drone ``drone_id`` of ``fleet`` (``recorder`` None: nothing recorded)."""

    def __init__(self, fleet: str, drone_id: str, bus: Any, recorder: Any = None):
        self.fleet = fleet
        self.drone_id = drone_id
        self.bus = bus
        self.recorder = recorder
        self._record_failed = False
        #: () -> a new recorder in place of a failed one (None: no recording after a failure)
        self.reopen_recorder: Callable[[], Any] | None = None
        self.reopen_interval_s = 5.0
        #: (text) -> None: a recording failure, reported once per failure (the agent's health warnings)
        self.on_record_failure: Callable[[str], None] | None = None
        self.recorder_failures: list[str] = []
        self._t_next_reopen_s = 0.0
        self._reopen_error = ""
        #: the recording folder (free space reported even while no recording is open); None: the recorder's folder
        self.record_dir: str | Path | None = None
        #: why nothing is recorded when no recorder was ever given (e.g. recording disabled in the config)
        self.no_recorder_reason = "no recorder configured"
        self.disk_free = DiskFree()

    def key(self, topic: str) -> str:
        """This drone's key of ``topic``."""
        return keys.drone_key(self.fleet, self.drone_id, topic)

    def record(self, key: str, data: bytes, log_time_ns: int | None = None) -> None:
        """Record bytes as sent/received on the recorder channel of ``key`` (``state``, ``gcs/cmd`` ...)."""
        if self.recorder is None or self._record_failed:
            if not self._reopen():
                return
        try:
            self.recorder.record(channel_name(key, self.drone_id), data, log_time_ns)
        except Exception as e:
            self._failed(f"recording to {getattr(self.recorder, 'path', '?')} failed: {e}")
            if self._reopen():
                try:
                    self.recorder.record(channel_name(key, self.drone_id), data, log_time_ns)
                except Exception as e2:
                    self._failed(f"recording to {getattr(self.recorder, 'path', '?')} failed: {e2}")

    def _failed(self, text: str) -> None:
        if self._record_failed:
            return
        self._record_failed = True
        log.error("%s: %s", self.drone_id, text)
        self.recorder_failures.append(text)
        if self.on_record_failure is not None:
            self.on_record_failure(f"recorder: {text}")
        old, self.recorder = self.recorder, None
        if old is not None:
            try:
                old.close()  # the writer's error again, or the summary written: either way the file is let go
            except Exception as e:
                log.debug("%s: closing the failed recorder: %s", self.drone_id, e)

    def detach_recorder(self) -> Any:
        """Shutdown: the recorder in use (a failed one was replaced; None if none is open) handed to the caller to
        close, and no recording from now on. What other threads still record after this (a message received while
        the transport closes) is dropped: it must not count as a failure and open a new sortie file."""
        rec, self.recorder = (None if self._record_failed else self.recorder), None
        self.reopen_recorder = None
        self._record_failed = False
        return rec

    def _reopen(self) -> bool:
        """A new recorder in place of the failed one (at most every ``reopen_interval_s``); whether one is open."""
        if self.recorder is not None and not self._record_failed:
            return True
        if self.reopen_recorder is None or time.monotonic() < self._t_next_reopen_s:
            return False
        self._t_next_reopen_s = time.monotonic() + self.reopen_interval_s
        try:
            rec = self.reopen_recorder()
        except Exception as e:
            if str(e) != self._reopen_error:
                self._reopen_error = str(e)
                log.error("%s: cannot open a new recording: %s", self.drone_id, e)
                if self.on_record_failure is not None:
                    self.on_record_failure(f"recorder: cannot open a new recording: {e}")
            return False
        self.recorder, self._record_failed, self._reopen_error = rec, False, ""
        log.warning("%s: recording again, into %s", self.drone_id, getattr(rec, "path", rec))
        return True

    def publish(self, topic: str, msg: Message, latch: bool = False) -> None:
        """Publish on this drone's ``topic`` and record what was sent."""
        key = self.key(topic)
        try:
            data = self.bus.publish(key, msg, latch=latch)
        except Exception as e:  # a dead network must not stop the flight
            log.warning("%s: publish on %s failed: %s", self.drone_id, key, e)
            data = encode(stamp_sent(msg))
        self.record(key, data)

    def recorder_status(self) -> RecorderStatus:
        """The recording as the agent's health reports it (never blocks: see :class:`DiskFree`)."""
        rec = None if self._record_failed else self.recorder
        folder = self.record_dir
        if folder is None and self.recorder is not None and getattr(self.recorder, "path", None) is not None:
            folder = Path(self.recorder.path).parent
        free = self.disk_free.get(folder) if folder is not None else -1
        if rec is None:
            if self.recorder_failures or self._reopen_error:
                error = self._reopen_error and f"cannot open a new recording: {self._reopen_error}"
                error = error or self.recorder_failures[-1]
                return RecorderStatus(recording=False, free_disk_bytes=free, ok=False, error=error)
            return RecorderStatus(recording=False, free_disk_bytes=free, ok=True, error=self.no_recorder_reason)
        try:
            st = rec.stats()
        except Exception as e:  # a recorder that cannot even count: reported, never raised into the health loop
            log.warning("%s: recorder statistics unavailable: %s", self.drone_id, e)
            st = {}
        error = str(getattr(rec, "error", "") or "")  # the writer failed; the next record() will notice
        path = getattr(rec, "path", None)
        return RecorderStatus(
            file=Path(path).name if path is not None else "", recording=True,
            bytes_written=int(st.get("bytes", 0)), messages_written=int(st.get("written", 0)),
            dropped=int(st.get("dropped", 0)), free_disk_bytes=free, ok=not error,
            error=f"recording to {path} failed: {error}" if error else self.disk_free.error,
        )
