"""The malformed-message flood of the fault suite: every kind is refused by the codec (nothing reaches an agent)."""

from __future__ import annotations

import pytest

from comms.faults import MalformedFloodInjector
from shared_msgs import keys
from shared_msgs.codec import MessageError, decode


class _Bus:
    def __init__(self):
        self.sent = []

    def publish_raw(self, key, data):
        self.sent.append((key, data))


def test_every_flood_message_is_refused_by_the_codec_on_the_keys_agents_listen_to():
    bus = _Bus()
    inj = MalformedFloodInjector(bus, "f", ["drone_1", "drone_2"], rate_hz=100.0)
    for k in range(8):
        inj.tick(k * 0.0125)
    assert inj.counts == {k: 2 for k in MalformedFloodInjector.KINDS}
    assert {key for key, _ in bus.sent} == {keys.drone_key("f", "drone_2", keys.STATE), keys.gcs_key("f", keys.CMD)}
    for key, data in bus.sent:
        with pytest.raises(MessageError):
            decode(data, source=key)
