"""The agent's components, each alone: the outbox (publishing + recording), the teammates' states, the setpoint
source chosen by ``mode``, the formation failsafes and the tracking capture (no network, no autopilot)."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import time

import numpy as np
import pytest

from flightdata.recorder import channel_name
from groundstation.fleet import make_orbit_plan
from onboard.agent import Agent
from onboard.agent.failsafes import FormationFailsafes
from onboard.agent.outbox import DiskFree, Outbox
from onboard.agent.teammates import Teammates
from onboard.agent.telemetry import Telemetry
from onboard.agent.tracking import TrackingCapture
from onboard.config import AgentConfig, FormationFailsafeConfig, TrackConfig
from onboard.formation.failsafe import FailsafeLog
from onboard.formation.source import FormationSource
from onboard.orbit import OrbitController
from onboard.setpoint import HoldSource
from shared_msgs import Health, VehicleState, decode, encode, keys


class FakeBus:
    def __init__(self, fail: bool = False):
        self.fail = fail
        self.sent: list[tuple[str, object]] = []

    def publish(self, key, msg, latch=False):
        if self.fail:
            raise ConnectionError("network down")
        self.sent.append((key, msg))
        return encode(msg)


class FakeRecorder:
    def __init__(self, fail: bool = False):
        self.fail = fail
        self.records: list[tuple[str, bytes, int | None]] = []

    def record(self, channel, data, log_time_ns=None):
        if self.fail:
            raise OSError("disk full")
        self.records.append((channel, data, log_time_ns))


class FakeAutopilot:
    def __init__(self):
        self.telemetry = Telemetry(armed=True, in_air=True, flight_mode="OFFBOARD", landed_state="in_air",
                                   position_ned_m=(8.0, 0.0, -6.0), health_ok=True)
        self.on_state = None
        self.mode_changes: list = []


def _state(d: str, pos, t_ns: int | None = None, vel=(0.0, 0.0, 0.0), landed="in_air", cov=(1.0, 1.0, 1.0)):
    return VehicleState(header=VehicleState.make_header(d, t_ns), position_ned_m=tuple(pos), velocity_ned_m_s=tuple(vel),
                        q_world_body=(1.0, 0.0, 0.0, 0.0), landed_state=landed, position_cov_m2=tuple(cov))


# --- outbox ----------------------------------------------------------------------------------------------
def test_outbox_publishes_and_records_what_it_sent_even_when_the_network_is_down(caplog):
    rec, bus = FakeRecorder(), FakeBus()
    out = Outbox("f", "drone_1", bus, rec)
    assert out.key(keys.HEALTH) == keys.drone_key("f", "drone_1", keys.HEALTH)
    h = Health(header=Health.make_header("drone_1"), role="agent", state="idle", ok=True)
    out.publish(keys.HEALTH, h)
    assert bus.sent == [(out.key(keys.HEALTH), h)]
    assert rec.records[-1][0] == channel_name(out.key(keys.HEALTH), "drone_1")
    bus.fail = True
    out.publish(keys.HEALTH, h)  # a dead network: logged, still recorded
    assert len(rec.records) == 2 and len(bus.sent) == 1
    rec.fail = True
    with caplog.at_level(logging.ERROR):
        for _ in range(3):
            out.record(out.key(keys.STATE), b"x")
    assert sum("recording to" in r.message for r in caplog.records) == 1  # a failing recorder: said once
    Outbox("f", "drone_1", FakeBus(), None).record("k", b"x")  # no recorder: nothing to do


def test_outbox_replaces_a_failed_recorder_and_reports_it():
    first, second = FakeRecorder(), FakeRecorder()
    made = [second]
    warnings: list[str] = []
    out = Outbox("f", "drone_1", FakeBus(), first)
    out.on_record_failure = warnings.append
    out.reopen_recorder = lambda: made.pop(0) if made else (_ for _ in ()).throw(OSError("No space left on device"))
    out.reopen_interval_s = 0.05
    out.record(out.key(keys.STATE), b"a")
    first.fail = True
    out.record(out.key(keys.STATE), b"b")  # fails on the first, goes to the new one at once
    assert [r[1] for r in first.records] == [b"a"] and [r[1] for r in second.records] == [b"b"]
    assert out.recorder is second and len(warnings) == 1 and "disk full" in warnings[0]
    second.fail = True
    for _ in range(3):
        out.record(out.key(keys.STATE), b"c")  # no new recording can be opened (disk full): reported once
        time.sleep(0.06)
    assert out.recorder is None
    assert sum("cannot open a new recording" in w for w in warnings) == 1, warnings
    made.append(FakeRecorder())  # room again: the next try records
    time.sleep(0.06)
    out.record(out.key(keys.STATE), b"d")
    assert out.recorder is not None and out.recorder.records[-1][1] == b"d"


def test_outbox_after_detach_records_nothing_and_opens_no_new_sortie():
    """At shutdown the recorder is detached, then closed: a message that another thread records meanwhile (the
    transport still delivering) is dropped, not a failure that opens a new sortie file."""
    rec = FakeRecorder()
    opened: list[FakeRecorder] = []
    out = Outbox("f", "drone_1", FakeBus(), rec)
    out.reopen_recorder = lambda: opened.append(FakeRecorder()) or opened[-1]
    out.reopen_interval_s = 0.0
    out.record(out.key(keys.STATE), b"a")
    assert out.detach_recorder() is rec
    rec.fail = True  # closed
    out.record(out.key(keys.STATE), b"b")
    assert [r[1] for r in rec.records] == [b"a"] and opened == [] and out.recorder_failures == []
    failed = Outbox("f", "drone_1", FakeBus(), FakeRecorder(fail=True))
    failed.record(failed.key(keys.STATE), b"x")
    assert failed.detach_recorder() is None  # a failed recorder was already let go


class StatsRecorder(FakeRecorder):
    """A recorder with the real one's reporting surface: ``path``, ``stats()``, ``error``."""

    def __init__(self, path, fail: bool = False):
        super().__init__(fail)
        self.path = path
        self.error = ""

    def record(self, channel, data, log_time_ns=None):
        super().record(channel, data, log_time_ns)

    def stats(self):
        return {"written": len(self.records), "bytes": sum(len(r[1]) for r in self.records), "dropped": 3,
                "invalid": 0, "flushes": 1, "queued_bytes": 0}

    def close(self):
        pass


class FakeUsage:
    def __init__(self, free: int, delay_s: float = 0.0, fail: str = ""):
        self.free_bytes, self.delay_s, self.fail, self.calls = free, delay_s, fail, []

    def __call__(self, path):
        self.calls.append(path)
        time.sleep(self.delay_s)
        if self.fail:
            raise OSError(self.fail)
        return type("Usage", (), {"free": self.free_bytes, "total": 10 * self.free_bytes, "used": 0})()


def _health_roundtrip(agent: Agent) -> Health:
    return decode(encode(agent.health()), Health)  # what the ground station gets: valid on the wire


def test_health_reports_the_recording_its_counters_and_the_record_folders_free_space(tmp_path):
    cfg = AgentConfig(drone_id="drone_1", fleet="f")
    cfg.record.dir = str(tmp_path)
    rec = StatsRecorder(tmp_path / "sortie-002_drone_1.mcap")
    agent = Agent(cfg, FakeBus(), FakeAutopilot(), rec)
    usage = FakeUsage(free=7 * 2**30, delay_s=0.2)
    agent.outbox.disk_free = DiskFree(interval_s=60.0, disk_usage=usage)
    agent.outbox.record(agent.outbox.key(keys.STATE), b"12345")
    agent.outbox.record(agent.outbox.key(keys.STATE), b"678")
    first = _health_roundtrip(agent).recorder
    assert first.free_disk_bytes == -1  # measured in the background: not known yet, never waited for
    agent.outbox.disk_free.wait()
    r = _health_roundtrip(agent).recorder
    assert (r.file, r.recording, r.ok, r.error) == ("sortie-002_drone_1.mcap", True, True, "")
    assert (r.messages_written, r.bytes_written, r.dropped) == (2, 8, 3)
    assert r.free_disk_bytes == 7 * 2**30 and usage.calls == [str(tmp_path)]
    for _ in range(5):
        agent.health()
    assert len(usage.calls) == 1  # at most every interval_s
    rec.error = "I/O error"  # the writer thread died: reported before the next record() notices
    r = agent.health().recorder
    assert not r.ok and "I/O error" in r.error and r.recording


def test_health_reports_a_failed_recorder_and_a_recording_that_cannot_be_reopened(tmp_path):
    cfg = AgentConfig(drone_id="drone_1", fleet="f")
    cfg.record.dir = str(tmp_path)
    agent = Agent(cfg, FakeBus(), FakeAutopilot(), StatsRecorder(tmp_path / "a.mcap", fail=True))
    agent.outbox.disk_free = DiskFree(disk_usage=FakeUsage(free=10**9))
    agent.outbox.record(agent.outbox.key(keys.STATE), b"x")  # fails; no reopen configured
    r = _health_roundtrip(agent).recorder
    assert not r.recording and not r.ok and "disk full" in r.error and r.file == ""
    agent.outbox.reopen_recorder = lambda: (_ for _ in ()).throw(OSError("No space left on device"))
    agent.outbox.reopen_interval_s = 0.0
    agent.outbox.record(agent.outbox.key(keys.STATE), b"y")
    r = agent.health().recorder
    assert not r.ok and r.error.startswith("cannot open a new recording") and "No space left" in r.error
    agent.outbox.disk_free.wait()
    assert agent.health().recorder.free_disk_bytes == 10**9  # the folder's space is still reported


def test_health_says_why_nothing_is_recorded_when_recording_is_disabled():
    cfg = AgentConfig(drone_id="drone_1", fleet="f")
    cfg.record.enabled = False
    r = Agent(cfg, FakeBus(), FakeAutopilot()).health().recorder
    assert not r.recording and r.free_disk_bytes == -1 and "record.enabled = false" in r.error


def test_disk_free_never_blocks_and_reports_a_failure():
    slow = DiskFree(disk_usage=FakeUsage(free=5, delay_s=0.3))
    t0 = time.perf_counter()
    assert slow.get("/x") == -1
    assert time.perf_counter() - t0 < 0.1
    slow.wait()
    assert slow.get("/x") == 5
    bad = DiskFree(disk_usage=FakeUsage(free=5, fail="stale file handle"))
    bad.get("/y")
    bad.wait()
    assert bad.get("/y") == -1 and "stale file handle" in bad.error


class FakeDetectorWorker:
    def __init__(self, name: str):
        self.detector = type("Det", (), {"name": name, "session": object()})()
        self.counts = {"submitted": 0, "dropped_busy": 0, "failed": 0, "done": 0}
        self._closed = False

    def close(self, wait: bool = True):
        self._closed = True


def test_health_reports_the_onboard_detector_or_why_there_is_none():
    orbit = Agent(AgentConfig(drone_id="drone_1", fleet="f"), FakeBus(), FakeAutopilot())
    d = _health_roundtrip(orbit).detector
    assert (d.required, d.loaded, d.model) == (False, False, "none (orbit mode: simulated keypoints)")
    track = Agent(AgentConfig(drone_id="drone_1", fleet="f", mode="track"), FakeBus(), FakeAutopilot())
    d = _health_roundtrip(track).detector
    assert not d.required and not d.loaded and "simulator's detections" in d.model
    track.tracking.detector_worker = FakeDetectorWorker("nanodet")  # track.detections = "onnx": a model loaded
    d = _health_roundtrip(track).detector
    assert (d.required, d.loaded, d.model, d.error) == (True, True, "nanodet", "")
    track.tracking.detector_worker.counts["failed"] = 2
    track.tracking.detector_worker.close()
    d = track.health().detector
    assert d.required and not d.loaded and "closed" in d.error


# --- teammates -------------------------------------------------------------------------------------------
def test_teammates_keep_the_others_latest_states():
    tm = Teammates("drone_1")
    tm.note("drone_1", _state("drone_1", (0, 0, -5)), 1.0, 100.0)  # our own: not a teammate
    a = _state("drone_2", (1, 2, -5))
    tm.note("drone_2", a, 2.0, 200.0)
    b = _state("drone_2", (3, 2, -5))
    tm.note("drone_2", b, 3.0, 300.0)
    assert tm.states == {"drone_2": b} and tm.seen_unix_s == {"drone_2": 300.0}
    assert tm.positions == {"drone_2": ((3.0, 2.0, -5.0), 3.0)}


# --- setpoint source by mode ------------------------------------------------------------------------------
def test_the_setpoint_source_follows_the_configured_mode():
    plan = make_orbit_plan(["drone_1"], (0.0, 0.0, 0.0), 8.0, 6.0, 0.2, 1)
    st = _state("drone_1", (8.0, 0.0, -6.0), int(time.time() * 1e9))
    t = time.time()

    orbit = Agent(AgentConfig(drone_id="drone_1", fleet="f"), FakeBus(), FakeAutopilot())
    assert orbit.tracking is None and orbit.formation is None and orbit.failsafes is None
    assert "detections" not in orbit.rates
    src = asyncio.run(orbit.source_for(plan))
    assert isinstance(src, OrbitController)
    ref = OrbitController(plan, "drone_1", orbit.cfg.flight.approach_speed_m_s, orbit.cfg.flight.approach_climb_m_s)
    sp, sp_ref = orbit.next_setpoint(src, t, st), ref.update(t, np.asarray(st.position_ned_m), np.zeros(3), 0.0)
    np.testing.assert_array_equal(sp.position_ned_m, sp_ref.position_ned_m)
    assert sp.yaw_rad == sp_ref.yaw_rad and sp.gimbal_pitch_rad == sp_ref.gimbal_pitch_rad

    bus = FakeBus()
    track = Agent(AgentConfig(drone_id="drone_1", fleet="f", mode="track"), bus, FakeAutopilot())
    assert track.rates["detections"] is track.tracking.detections_rate
    src = asyncio.run(track.source_for(plan))
    assert isinstance(src, FormationSource) and track.failsafes.active
    # a pause's hold in track mode: flown as it is (no offset, no MPC step, nothing shared)
    hold = HoldSource((1.0, 2.0, -5.0), 0.3)
    sp = track.next_setpoint(hold, t, st)
    np.testing.assert_array_equal(sp.position_ned_m, [1.0, 2.0, -5.0])
    assert sp.yaw_rad == 0.3 and bus.sent == [] and track.formation.mpc_solve_ms == []
    # the formation source: one MPC step, its plan shared with the teammates
    sp = track.next_setpoint(src, t, st)
    assert np.all(np.isfinite(sp.position_ned_m)) and len(track.formation.mpc_solve_ms) == 1
    assert [k for k, _ in bus.sent] == [keys.drone_key("f", "drone_1", keys.FORMATION_PLAN)]
    stats = track.tracking_stats()
    assert stats["mode"] == "track" and stats["detections_source"] == "sim" and len(stats["mpc_solve_ms"]) == 1
    assert orbit.tracking_stats()["mpc_solve_ms"] == [] and orbit.tracking_stats()["failsafe_events"] == []


# --- formation failsafes ----------------------------------------------------------------------------------
class FakeFormationSource:
    """What the failsafes act on: slot angle, hold / search (the FormationSource's interface)."""

    def __init__(self):
        self.slot_angle_rad = 0.0
        self.hold_position_ned_m = None
        self.search_yaw_rate_rad_s = 0.0
        self.last_result = None

    @property
    def holding(self):
        return self.hold_position_ned_m is not None

    def hold(self, position_ned_m=None, search_yaw_rate_rad_s=0.0):
        self.hold_position_ned_m = None if position_ned_m is None else np.asarray(position_ned_m, float)
        self.search_yaw_rate_rad_s = search_yaw_rate_rad_s if position_ned_m is not None else 0.0


def test_formation_failsafes_alone():
    mission, warnings = [], []
    fs = FormationFailsafes("drone_1", FormationFailsafeConfig(), lambda r, a: mission.append((r, a)), warnings.append)
    plan = make_orbit_plan(["drone_1"], (0.0, 0.0, 0.0), 8.0, 6.0, 0.0, 1)
    assert not fs.active
    t0 = 1000.0
    fs.start(plan, t0)
    assert fs.active and fs.t_formation_start_s == t0
    src, own = FakeFormationSource(), np.array([8.0, 0.0, -6.0])

    def step(t_s, battery=0.9):
        inp = fs.inputs(t_s, own, estimate=None, person_guess_ned_m=np.zeros(3), src=src, teammate_states={},
                        teammates_seen_s={}, battery_remaining_frac=battery, operator_angles_rad={"drone_1": 0.0},
                        consecutive_fallbacks=0)
        fs.act(src, inp, own)

    step(t0 + 1.0)  # within the acquisition grace time: fly on
    assert not src.holding and fs.log.events == [] and fs.last_response.hold is False
    step(t0 + 25.0)  # never seen after the grace time: hold and search
    assert src.holding and src.search_yaw_rate_rad_s == math.radians(30.0)
    np.testing.assert_array_equal(src.hold_position_ned_m, own)
    assert fs.log.events[-1]["action"] == "hold_and_search" and "hold_and_search" in warnings[-1]
    step(t0 + 26.0, battery=0.2)  # low battery: return through the mission
    assert mission and mission[-1][1] == "return" and fs.log.counts["return"] == 1
    off = FormationFailsafes("drone_1", FormationFailsafeConfig(enabled=False), lambda r, a: None, warnings.append)
    off.start(plan, t0)
    assert not off.active and off.t_formation_start_s is None


# --- tracking capture -------------------------------------------------------------------------------------
def test_tracking_capture_alone_takes_a_gps_jump_back():
    published, warnings = [], []
    events = FailsafeLog("drone_1")
    cap = TrackingCapture("drone_1", TrackConfig(), lambda topic, msg: published.append(topic), events, warnings.append)
    assert cap.detector_worker is None and cap.stats()["detections_source"] == "sim"
    cap.on_state(_state("drone_1", (0.0, 0.0, -0.3), int(10e9), landed="on_ground", cov=(0.04, 0.04, 0.09)))
    assert cap.stage.own_ground_down_m == -0.3
    np.testing.assert_allclose(cap.stage.own_position_var_m2, [0.04, 0.04, 0.09])
    cap.on_state(_state("drone_1", (0.04, 0.0, -0.3), int(10.02e9), vel=(2.0, 0.0, 0.0)))  # explained by its speed
    assert events.events == [] and not cap.stage.position_correction(int(20e9)).any()
    cap.on_state(_state("drone_1", (3.08, 0.0, -0.3), int(10.04e9), vel=(2.0, 0.0, 0.0)))  # +3 m in 20 ms
    assert events.events[-1]["action"] == "gps_jump" and events.counts == {"estimator:gps_jump": 1}
    assert warnings and warnings[-1].startswith("GPS jump")
    np.testing.assert_allclose(cap.stage.position_correction(int(10.04e9)), [3.0, 0.0, 0.0], atol=0.02)
    cap.publish_target(100.0)  # no track yet: nothing to publish
    assert published == [] and cap.malformed_counts() == (0, 0)
    off = TrackingCapture("drone_1", TrackConfig(gps_jump_threshold_m=0.0), published.append, FailsafeLog("d"), warnings.append)
    off.on_state(_state("drone_1", (0.0, 0.0, -5.0), int(10e9)))
    off.on_state(_state("drone_1", (9.0, 0.0, -5.0), int(10.02e9)))
    assert not off.stage.position_correction(int(20e9)).any()


# --- vehicle supervisor -----------------------------------------------------------------------------------
def test_vehicle_supervisor_alone():
    from onboard.agent.supervisor import VehicleSupervisor
    from onboard.mission import Mission, State

    calls: list = []
    flowing, gap = [True], [0.05]
    ap = FakeAutopilot()
    ap.telemetry = Telemetry(armed=True, in_air=True, flight_mode="OFFBOARD", landed_state="in_air",
                             position_ned_m=(0.0, 0.0, -5.0), health_ok=True, battery_remaining_frac=0.9)
    ap.offboard_active, ap.offboard_since_s = True, 0.0
    mission, tm = Mission(), Teammates("drone_1")
    mission.set_plan(make_orbit_plan(["drone_1", "drone_2"], (0.0, 0.0, 0.0), 8.0, 6.0, 0.0, 1))
    mission.state = State.ORBIT
    sup = VehicleSupervisor(AgentConfig(drone_id="drone_1"), mission, ap, tm,
                            failsafe=lambda r, a: calls.append(("failsafe", a, r)),
                            stop_setpoints=lambda: calls.append(("stop",)), resume_offboard=lambda: calls.append(("resume",)),
                            setpoints_flowing=lambda: flowing[0], warn=lambda w: calls.append(("warn", w)),
                            setpoint_gap_s=lambda: gap[0])
    sup.on_gcs_heartbeat()
    sup.check()
    assert calls == [] and sup.gcs_seen
    # HOLD while our setpoints flowed without a gap: not our stall (a pilot, the autopilot's own reason): followed
    ap.telemetry = dataclasses.replace(ap.telemetry, flight_mode="HOLD")
    sup.check()
    assert calls[-1] == ("stop",) and mission.state == State.PAUSED and not ap.offboard_active
    assert sup.takeovers[-1]["mode"] == "HOLD" and not sup.takeovers[-1]["stalled"]
    # the autopilot's offboard-loss Return after a 2.5 s stall of ours: reported, then undone once the setpoints flow
    mission.state, ap.offboard_active, gap[0], flowing[0] = State.ORBIT, True, 2.5, False
    ap.telemetry = dataclasses.replace(ap.telemetry, flight_mode="RETURN_TO_LAUNCH")
    calls.clear()
    sup.check()
    assert calls == [] and mission.state == State.ORBIT  # waiting up to autopilot.resume_wait_s for the stream
    flowing[0] = True
    sup.check()
    assert calls[-1] == ("resume",) and mission.state == State.ORBIT
    assert "offboard-loss failsafe after a setpoint stall" in calls[0][1] and "switching back" in calls[0][1]
    # PX4 went back to OFFBOARD by itself before we did: reported
    calls.clear()
    ap.offboard_since_s, flowing[0] = 0.0, False
    ap.telemetry = dataclasses.replace(ap.telemetry, flight_mode="HOLD")
    sup.check()
    ap.telemetry = dataclasses.replace(ap.telemetry, flight_mode="OFFBOARD")
    sup.check()
    assert [c for c in calls if c[0] == "warn"] == [
        ("warn", "autopilot took over in HOLD (offboard-loss failsafe after a setpoint stall): autopilot back in "
                 f"OFFBOARD by itself after {0.0:.1f} s")] and mission.state == State.ORBIT
    # policy "follow": the stall's Return is followed
    follow_cfg = AgentConfig(drone_id="drone_1")
    follow_cfg.autopilot.on_failsafe = "follow"
    sup.cfg = follow_cfg
    flowing[0] = True
    ap.offboard_since_s = 0.0
    ap.telemetry = dataclasses.replace(ap.telemetry, flight_mode="RETURN_TO_LAUNCH")
    sup.check()
    assert mission.state == State.RETURNING and calls[-1] == ("stop",)
    sup.cfg = AgentConfig(drone_id="drone_1")
    mission.state, ap.offboard_active = State.ORBIT, True
    ap.telemetry = dataclasses.replace(ap.telemetry, flight_mode="OFFBOARD")
    # another drone too close: the configured separation action (hold)
    tm.note("drone_2", _state("drone_2", (1.0, 0.0, -5.0)), time.monotonic(), time.time())
    ap.telemetry = dataclasses.replace(ap.telemetry, flight_mode="OFFBOARD")
    calls.clear()
    sup.check()
    assert calls[0][:2] == ("failsafe", "hold") and "separation: drone_2" in calls[0][2]
    # the ground station falls silent; low battery
    calls.clear()
    sup.t_last_gcs_s -= 10.0
    ap.telemetry = dataclasses.replace(ap.telemetry, battery_remaining_frac=0.1)
    sup.check()
    assert [c[1] for c in calls if c[0] == "failsafe"][:2] == ["land", "land"]
    assert any("heartbeat lost" in c[2] for c in calls if c[0] == "failsafe")
    assert any("low battery 10%" in c[2] for c in calls if c[0] == "failsafe")


def test_supervisor_reports_a_stall_the_autopilot_recovered_from_unseen():
    """PX4 returns to OFFBOARD within a second when the setpoints resume: the mode seen may never change; the
    agent's own stall beyond COM_OF_LOSS_T is reported once as the autopilot's failsafe."""
    from onboard.agent.supervisor import VehicleSupervisor
    from onboard.mission import Mission, State

    warns, gap = [], [0.05]
    ap = FakeAutopilot()
    ap.offboard_active, ap.offboard_since_s = True, 0.0
    mission = Mission()
    mission.set_plan(make_orbit_plan(["drone_1"], (0.0, 0.0, 0.0), 8.0, 6.0, 0.0, 1))
    mission.state = State.ORBIT
    sup = VehicleSupervisor(AgentConfig(drone_id="drone_1"), mission, ap, Teammates("drone_1"), failsafe=lambda r, a: None,
                            stop_setpoints=lambda: None, resume_offboard=lambda: None, setpoints_flowing=lambda: True,
                            warn=warns.append, setpoint_gap_s=lambda: gap[0])
    sup.on_gcs_heartbeat()
    sup.check()
    gap[0] = 2.5
    sup.check()
    sup.check()  # once per stall
    assert len(warns) == 1 and "setpoints stalled for 2.5 s" in warns[0] and "offboard-loss failsafe" in warns[0]
    assert "its offboard-loss action (hold)" in warns[0] and mission.state == State.ORBIT


# --- statistics -------------------------------------------------------------------------------------------
def test_statistics_sum_the_subscriptions_counters():
    from comms.transport import TopicStats
    from onboard.agent.stats import malformed_detections, transport_counts

    class Sub:
        def __init__(self, key_expr, **counts):
            self.key_expr, self.stats = key_expr, TopicStats(**counts)

    subs = [Sub("f/drone/*/detections", received=10, malformed=2, fault_judged=5, fault_dropped=1),
            Sub("f/drone/drone_1/sim/detections", received=4, malformed=1, fault_delayed=2),
            Sub("f/drone/*/state", received=100, malformed=3)]
    assert transport_counts(subs) == {"received": 114, "malformed": 6, "fault_judged": 5, "fault_dropped": 1,
                                      "fault_delayed": 2}
    assert malformed_detections(subs, None) == {"refused_by_codec": 3, "invalid_content": 0,
                                                "nonfinite_measurements": 0, "total": 3}


def test_the_agent_keeps_every_setpoint_out_of_the_plans_zones_and_warns_once():
    from shared_msgs import GeofenceZone, KeepOutZone

    plan = make_orbit_plan(["drone_1"], (0.0, 0.0, 0.0), 8.0, 6.0, 0.2, 1)
    import msgspec

    plan = msgspec.structs.replace(plan, geofence=GeofenceZone(radius_m=30.0),
                                   keepout_zones=[KeepOutZone(name="shed", north_m=0.0, east_m=0.0, radius_m=3.0)])
    agent = Agent(AgentConfig(drone_id="drone_1", fleet="f"), FakeBus(), FakeAutopilot())
    agent.mission.set_plan(plan)
    st = _state("drone_1", (1.0, 0.0, -6.0), int(time.time() * 1e9))
    into = HoldSource((1.0, 0.0, -6.0), 0.0)  # a setpoint inside the shed's zone
    for _ in range(3):
        sp = agent.next_setpoint(into, time.time(), st)
        assert math.hypot(sp.position_ned_m[0], sp.position_ned_m[1]) == pytest.approx(3.5)
    assert agent.zone_clamps == 3
    assert agent.warnings == ["setpoint clamped: it would have entered keep-out zone 'shed'"]
    away = HoldSource((10.0, 0.0, -6.0), 0.0)  # fine: untouched
    np.testing.assert_array_equal(agent.next_setpoint(away, time.time(), st).position_ned_m, [10.0, 0.0, -6.0])
    assert agent.zone_clamps == 3
    # a track-mode agent: its setpoints pass the same clamp (after the formation's step)
    track = Agent(AgentConfig(drone_id="drone_1", fleet="f", mode="track"), FakeBus(), FakeAutopilot())
    track.mission.set_plan(msgspec.structs.replace(plan, mode="track", angular_speed_rad_s=0.0))
    sp = track.next_setpoint(into, time.time(), st)
    assert math.hypot(sp.position_ned_m[0], sp.position_ned_m[1]) == pytest.approx(3.5) and track.zone_clamps == 1
