"""The ground station's pre-flight checklist and fleet panel from the agents' Health (no Qt, no network):
"recorder space" and "detector" from Health version 2, and "not reported" (an older agent) failing."""

from __future__ import annotations

import threading

import pytest

from groundstation.app.config import GsConfig
from groundstation.app.model import FleetModel
from shared_msgs import DetectorStatus, Health, RecorderStatus, decode, encode

GB = 1_000_000_000


class FakeBus:
    secure = True

    def subscribe(self, key, cb, msg_type):
        return object()


class FakeClient:
    """What FleetModel reads of a FleetClient."""

    fleet = "f"
    heartbeat_hz = 2.0

    def __init__(self):
        self.bus = FakeBus()
        self._lock = threading.Lock()
        self.states: dict = {}
        self.healths: dict = {}
        self.last_rx_s: dict = {}
        self.alive: set = set()


def _model(min_free_disk_gb: float = 2.0, require_detector: bool = False) -> FleetModel:
    cfg = GsConfig(event_log="")
    cfg.checklist.min_free_disk_gb = min_free_disk_gb
    cfg.checklist.require_detector = require_detector
    return FleetModel(FakeClient(), cfg, clock=lambda: 100.0)


def _health(recorder=None, detector=None) -> Health:
    h = Health(header=Health.make_header("drone_1"), role="agent", state="idle", recorder=recorder, detector=detector)
    return decode(encode(h), Health)  # as received


REC = dict(file="sortie-001_drone_1.mcap", recording=True, bytes_written=12_500_000, messages_written=900, dropped=4)
ORBIT = DetectorStatus(required=False, model="none (orbit mode: simulated keypoints)")


def _check(m: FleetModel, h: Health | None, name: str):
    if h is not None:
        m.client.healths["drone_1"] = h
        m.client.last_rx_s["drone_1"] = 99.5
    return next(c for c in m.checklist("drone_1") if c.name == name)


def test_recorder_space_passes_with_enough_free_space_and_the_panel_shows_the_recording():
    m = _model(min_free_disk_gb=2.0)
    c = _check(m, _health(RecorderStatus(**REC, free_disk_bytes=5 * GB), ORBIT), "recorder space")
    assert c.ok and "5.0 GB free" in c.detail and "need ≥ 2 GB" in c.detail
    r = m.row("drone_1")
    assert (r.recorder_file, r.recorder_mb, r.recorder_dropped, r.free_disk_gb) == ("sortie-001_drone_1.mcap", 12.5, 4, 5.0)
    assert r.recorder == "sortie-001_drone_1.mcap, 12.5 MB, 4 dropped, 5.0 GB free"


@pytest.mark.parametrize("status, expect", [
    (RecorderStatus(**REC, free_disk_bytes=int(1.5 * GB)), "too little space: 1.5 GB free (need ≥ 2 GB)"),
    (RecorderStatus(**REC, free_disk_bytes=9 * GB, ok=False, error="recording to a.mcap failed: I/O error"),
     "recorder error: recording to a.mcap failed: I/O error"),
    (RecorderStatus(recording=False, free_disk_bytes=9 * GB, ok=False, error="cannot open a new recording: full"),
     "recorder error: cannot open a new recording: full"),
    (RecorderStatus(recording=False, free_disk_bytes=-1, error="recording disabled (record.enabled = false)"),
     "not recording: recording disabled"),
    (RecorderStatus(**REC, free_disk_bytes=-1), "free space unknown"),
])
def test_recorder_space_fails_with_the_reason(status, expect):
    c = _check(_model(), _health(status, ORBIT), "recorder space")
    assert not c.ok and expect in c.detail, c.detail


def test_an_agent_that_does_not_report_fails_both_checks_as_not_reported_until_overridden():
    m = _model()
    h1 = _health()  # Health version 1 decodes like this: recorder and detector None
    rec, det = _check(m, h1, "recorder space"), _check(m, None, "detector")
    assert not rec.ok and rec.detail.startswith("not reported") and not det.ok and det.detail.startswith("not reported")
    assert m.row("drone_1").recorder == "not reported" and m.row("drone_1").detector == "not reported"
    assert "recorder space" in m.precheck("takeoff", ["drone_1"])["drone_1"]
    m.override_checklist("drone_1", "disk checked by hand")
    assert m.precheck("takeoff", ["drone_1"]) == {}  # the operator's override (logged) lets it take off
    assert any("CHECKLIST OVERRIDE" in e.text and "recorder space: not reported" in e.text for e in m.events)
    m2 = _model()
    assert not _check(m2, None, "recorder space").ok  # no health at all: fails too


@pytest.mark.parametrize("det, require, ok, expect", [
    (DetectorStatus(required=True, loaded=True, model="nanodet", rate_hz=9.5), False, True, "nanodet loaded, 9.5 Hz"),
    (DetectorStatus(required=True, loaded=False, model="nanodet", error="the detector's worker is closed"), False,
     False, "nanodet expected, NOT loaded: the detector's worker is closed"),
    (ORBIT, False, True, "not needed: none (orbit mode: simulated keypoints)"),
    (ORBIT, True, False, "no onboard detector (none (orbit mode: simulated keypoints))"),
])
def test_detector_check(det, require, ok, expect):
    m = _model(require_detector=require)
    c = _check(m, _health(RecorderStatus(**REC, free_disk_bytes=5 * GB), det), "detector")
    assert c.ok == ok and expect in c.detail, c.detail
