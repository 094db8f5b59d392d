"""A restarted agent (systemd's Restart=on-failure, or the next flight into the same folder) records a new
sortie and never touches an earlier recording: once when the new start cannot reach its autopilot, once when
it flies."""

from __future__ import annotations

import hashlib
import signal
import time

import pytest

from flightdata.flightlog import FlightLog
from flightdata.folder import FlightFolder
from tests.helpers.ports import free_udp_base

pytestmark = pytest.mark.slow


def _digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _fly_and_stop(fl, *extra: str) -> None:
    t0_ns = time.time_ns()
    proc = fl.start_agent(0, *extra)
    assert fl.fleet.wait_until(lambda f: "drone_1" in f.states and f.states["drone_1"].header.t_sent_ns > t0_ns,
                               40, "drone_1 up"), fl.log("drone_1")
    time.sleep(2.0)  # record a couple of seconds of telemetry (50 Hz)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(40) == 0, fl.log("drone_1")


def test_agent_restarts_never_touch_the_earlier_recording(flight):
    fl = flight(1)
    folder = FlightFolder(fl.tmp)
    _fly_and_stop(fl)
    [first] = folder.sorties("drone_1")
    assert first.path.name == "drone_1.s001.mcap" and first.config_path.is_file()
    assert FlightLog(first.path).topic_counts().get("state", 0) > 10
    kept = _digest(first.path)

    # a start that cannot reach its autopilot (nothing listens there) fails, and leaves sortie 1 as it was
    nowhere = free_udp_base(1)
    proc = fl.start_agent(0, "--connection", f"udpin://0.0.0.0:{nowhere}", "--set", "connect_timeout_s=2")
    assert proc.wait(60) != 0
    assert "no autopilot heartbeat" in fl.log("drone_1")
    assert _digest(first.path) == kept
    assert [s.number for s in folder.sorties("drone_1")] == [1, 2]

    # and a start that flies records sortie 3, still leaving the others byte-identical
    second = folder.sorties("drone_1")[1]
    kept2 = _digest(second.path)
    _fly_and_stop(fl)
    sorties = folder.sorties("drone_1")
    assert [s.number for s in sorties] == [1, 2, 3]
    assert _digest(first.path) == kept and _digest(second.path) == kept2
    assert FlightLog(sorties[2].path).topic_counts().get("state", 0) > 10
