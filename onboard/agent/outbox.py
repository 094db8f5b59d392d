"""The agent's way out: its Zenoh keys, publishing on the bus and recording to its MCAP file.

Everything the agent sends or receives is recorded on the recorder channel of its key (``state``,
``gcs/cmd`` ...; :func:`flightdata.recorder.channel_name`). A dead network or a failing recorder never stops
the flight: publishing failures are logged; a recording failure is logged, reported (``on_record_failure``:
the agent's health warnings) and, with ``reopen_recorder``, a new recording (the next sortie file) is opened in
its place, at most every ``reopen_interval_s`` (a disk that stays full: retried as often, reported once).
"""

from __future__ import annotations

import logging
import time
from typing import Any, Callable

from flightdata.recorder import channel_name
from shared_msgs import Message, encode, keys, stamp_sent

log = logging.getLogger(__name__)

__all__ = ["Outbox"]


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
