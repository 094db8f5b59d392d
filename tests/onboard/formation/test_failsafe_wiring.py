"""How the agent acts on the formation failsafe (pure parts): response per action, the decision log, the
person-lost clock before the first detection, operator angles vs re-spacing, hold / search in the source."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onboard.formation.failsafe import (FailsafeAction, FailsafeInputs, FailsafeLog, FormationSupervisor, decide,
                                        person_seen_s, respond)
from onboard.formation.mpc import FormationMPC, MpcConfig, SharedPlan
from onboard.formation.source import FormationSource

POS = {"d0": (8.0, 0.0, -8.0), "d1": (-4.0, 6.9, -8.0), "d2": (-4.0, -6.9, -8.0)}
OP = {"d0": 0.1, "d1": 2.2, "d2": -2.0}


def inputs(**kw):
    base = dict(t_s=100.0, self_id="d0", t_person_seen_s=99.8, teammates_last_seen_s={"d1": 99.9, "d2": 99.95},
                battery_frac=0.8, positions_ned_m=POS, operator_angles_rad=OP)
    base.update(kw)
    return FailsafeInputs(**base)


def test_operator_angles_while_all_present_then_equal_spacing_after_a_loss():
    sup = FormationSupervisor("d0")
    d = sup.update(inputs())
    assert d.action is FailsafeAction.CONTINUE and d.slot_angles_rad == pytest.approx(OP)
    d = sup.update(inputs(t_s=103.0, t_person_seen_s=102.9, teammates_last_seen_s={"d1": 102.9, "d2": 99.95}))
    assert d.action is FailsafeAction.RESPACE and set(d.slot_angles_rad) == {"d0", "d1"}
    gap = abs((d.slot_angles_rad["d0"] - d.slot_angles_rad["d1"] + math.pi) % (2 * math.pi) - math.pi)
    assert abs(gap - math.pi) < 1e-9 and d.slot_angles_rad["d0"] != OP["d0"]


def test_response_per_action():
    d = decide(inputs(), ("d0", "d1", "d2"))
    r = respond(d, "d0")
    assert not r.hold and not r.search and r.mission_action is None and r.slot_angle_rad == pytest.approx(OP["d0"])
    r = respond(decide(inputs(t_person_seen_s=90.0), ("d0", "d1", "d2")), "d0")
    assert r.hold and r.search and r.mission_action is None
    r = respond(decide(inputs(predicted_min_separation_m=3.1), ("d0", "d1", "d2")), "d0")
    assert r.hold and not r.search
    assert respond(decide(inputs(battery_frac=0.2), None), "d0").mission_action == "return"
    assert respond(decide(inputs(battery_frac=0.05), None), "d0").mission_action == "land"


def test_person_lost_clock_before_the_first_detection():
    # never seen: lost only acquire_grace_s after the start
    t = person_seen_s(None, 1000.0, 20.0, 3.0)
    assert decide(inputs(t_s=1019.0, t_person_seen_s=t, teammates_last_seen_s={}), None).action is FailsafeAction.CONTINUE
    assert decide(inputs(t_s=1020.5, t_person_seen_s=t, teammates_last_seen_s={}), None).action is FailsafeAction.HOLD_AND_SEARCH
    assert person_seen_s(1012.5, 1000.0, 20.0, 3.0) == 1012.5


def test_log_keeps_changes_only_and_counts():
    log = FailsafeLog("d0")
    sup = FormationSupervisor("d0")
    assert log.note(100.0, sup.update(inputs())) is None  # the normal start is no event
    assert log.note(100.05, sup.update(inputs(t_s=100.05))) is None
    ev = log.note(104.0, sup.update(inputs(t_s=104.0, t_person_seen_s=100.0, teammates_last_seen_s={"d1": 104, "d2": 104})))
    assert ev["action"] == "hold_and_search" and "person lost" in ev["reasons"][0]
    assert log.note(104.05, sup.update(inputs(t_s=104.05, t_person_seen_s=100.0, teammates_last_seen_s={"d1": 104, "d2": 104}))) is None
    ev = log.note(105.0, sup.update(inputs(t_s=105.0, t_person_seen_s=104.9, teammates_last_seen_s={"d1": 104.9})))
    assert ev["action"] == "respace" and ev["present"] == ["d0", "d1"] and ev["slot_angle_rad"] is not None
    log.add(106.0, "land", ["ground-station heartbeat lost"], source="mission")
    assert log.counts == {"hold_and_search": 1, "respace": 1, "mission:land": 1} and len(log.events) == 3


def test_source_hold_search_and_shared_hold_plan():
    src = FormationSource(FormationMPC("d0", MpcConfig(max_solve_time_s=1.0)), slot_angle_rad=0.0)
    src.set_target([0.0, 0.0, -0.85], [0.0, 0.0, 0.0])
    p, v = np.array([8.0, 0.0, -6.0]), np.zeros(3)
    src.update(1000.0, p, v, math.pi)
    assert not src.holding and src.shared_plan is src.last_plan
    src.hold(p, search_yaw_rate_rad_s=0.5)
    sp = src.update(1000.1, p + 0.3, v, 1.0)
    np.testing.assert_array_equal(sp.position_ned_m, p)  # brakes back to where the hold began
    assert abs(sp.yaw_rad - 1.25) < 1e-9  # turning: leads the heading by 0.5 s of the search rate
    sh = src.shared_plan
    assert sh.positions_ned_m.shape == src.last_plan.positions_ned_m.shape
    np.testing.assert_array_equal(sh.positions_ned_m, np.tile(p, (len(sh.positions_ned_m), 1)))
    assert src.last_result.plan.t0_ns == int(1000.1e9)  # the MPC keeps planning while holding
    src.hold(p)  # hold without search: faces the person
    sp = src.update(1000.2, p, v, 1.0)
    assert abs(sp.yaw_rad - math.pi) < 1e-9
    src.hold(None)
    assert not src.holding and src.search_yaw_rate_rad_s == 0.0
    src.set_teammate_plan(SharedPlan("d1", int(1000.2e9), 0.1, np.tile([[-8.0, 0.0, -6.0]], (16, 1))))
    sp = src.update(1000.3, p, v, 1.0)
    assert np.linalg.norm(sp.position_ned_m - p) < 1.0 and src.last_result.min_teammate_distance_m > 10.0
