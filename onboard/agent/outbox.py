"""The agent's way out: its Zenoh keys, publishing on the bus and recording to its MCAP file.

Everything the agent sends or receives is recorded on the recorder channel of its key (``state``,
``gcs/cmd`` ...; :func:`flightdata.recorder.channel_name`). A dead network or a failing recorder never stops
the flight: publishing failures are logged, a recording failure is logged once.
"""

from __future__ import annotations

import logging
from typing import Any

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

    def key(self, topic: str) -> str:
        """This drone's key of ``topic``."""
        return keys.drone_key(self.fleet, self.drone_id, topic)

    def record(self, key: str, data: bytes, log_time_ns: int | None = None) -> None:
        """Record bytes as sent/received on the recorder channel of ``key`` (``state``, ``gcs/cmd`` ...)."""
        if self.recorder is None:
            return
        try:
            self.recorder.record(channel_name(key, self.drone_id), data, log_time_ns)
        except Exception as e:
            if not self._record_failed:
                log.error("%s: recording on %s failed: %s", self.drone_id, key, e)
                self._record_failed = True

    def publish(self, topic: str, msg: Message, latch: bool = False) -> None:
        """Publish on this drone's ``topic`` and record what was sent."""
        key = self.key(topic)
        try:
            data = self.bus.publish(key, msg, latch=latch)
        except Exception as e:  # a dead network must not stop the flight
            log.warning("%s: publish on %s failed: %s", self.drone_id, key, e)
            data = encode(stamp_sent(msg))
        self.record(key, data)
