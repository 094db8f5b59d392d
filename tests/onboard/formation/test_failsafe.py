import math

import numpy as np
import pytest

from onboard.formation.failsafe import FailsafeAction, FailsafeConfig, FailsafeInputs, FormationSupervisor, decide
from onboard.formation.slots import SlotError, assign_slot_angles


def inputs(**kw):
    base = dict(
        t_s=100.0,
        self_id="d0",
        t_person_seen_s=99.8,
        teammates_last_seen_s={"d1": 99.9, "d2": 99.95},
        battery_frac=0.8,
        positions_ned_m={"d0": (8.0, 0.0, -8.0), "d1": (-4.0, 6.9, -8.0), "d2": (-4.0, -6.9, -8.0)},
    )
    base.update(kw)
    return FailsafeInputs(**base)


ALL = ("d0", "d1", "d2")


def test_continue_when_all_well():
    d = decide(inputs(), ALL)
    assert d.action is FailsafeAction.CONTINUE and d.reasons == () and d.present_ids == ALL


def test_person_lost_hold_and_search():
    d = decide(inputs(t_person_seen_s=96.0), ALL)
    assert d.action is FailsafeAction.HOLD_AND_SEARCH and "person lost" in d.reasons[0]
    assert decide(inputs(t_person_seen_s=None), ALL).action is FailsafeAction.HOLD_AND_SEARCH
    assert decide(inputs(t_person_seen_s=97.5), ALL).action is FailsafeAction.CONTINUE


def test_teammate_lost_respaces_among_present():
    d = decide(inputs(teammates_last_seen_s={"d1": 99.9, "d2": 97.0}), ALL)
    assert d.action is FailsafeAction.RESPACE and d.present_ids == ("d0", "d1")
    a = d.slot_angles_rad
    assert set(a) == {"d0", "d1"}
    diff = abs((a["d0"] - a["d1"] + math.pi) % (2 * math.pi) - math.pi)
    assert abs(diff - math.pi) < 1e-9  # two drones: opposite sides
    # first call (no previous set) does not trigger re-spacing
    assert decide(inputs(), None).action is FailsafeAction.CONTINUE
    # a teammate joining also re-spaces
    assert decide(inputs(), ("d0", "d1")).action is FailsafeAction.RESPACE


def test_breach_imminent_holds_and_priorities():
    assert decide(inputs(predicted_geofence_margin_m=0.2), ALL).action is FailsafeAction.HOLD
    assert decide(inputs(predicted_min_separation_m=3.2), ALL).action is FailsafeAction.HOLD
    assert decide(inputs(predicted_min_separation_m=3.6), ALL).action is FailsafeAction.CONTINUE
    assert decide(inputs(consecutive_fallbacks=5), ALL).action is FailsafeAction.HOLD
    # hold beats search; low battery beats hold; critical battery lands
    d = decide(inputs(predicted_geofence_margin_m=0.0, t_person_seen_s=50.0), ALL)
    assert d.action is FailsafeAction.HOLD and len(d.reasons) == 2
    assert decide(inputs(battery_frac=0.2, predicted_geofence_margin_m=0.0), ALL).action is FailsafeAction.RETURN
    assert decide(inputs(battery_frac=0.1), ALL).action is FailsafeAction.LAND
    assert decide(inputs(battery_frac=float("nan")), ALL).action is FailsafeAction.RETURN


def test_slot_angles_equal_and_close_to_current_positions():
    pos = {"a": np.array([10.0, 1.0, -8]), "b": np.array([-5.0, 8.0, -8]), "c": np.array([-5.0, -8.0, -8])}
    a = assign_slot_angles(["c", "a", "b"], np.zeros(3), pos)
    ang = sorted(a.values())
    steps = np.diff(ang + [ang[0] + 2 * math.pi])
    np.testing.assert_allclose(steps, 2 * math.pi / 3, atol=1e-9)
    for i, p in pos.items():
        bearing = math.atan2(p[1], p[0])
        assert abs((a[i] - bearing + math.pi) % (2 * math.pi) - math.pi) < 0.3
    # operator angles win when they cover everyone
    op = {"a": 0.0, "b": 1.0, "c": 4.0}
    got = assign_slot_angles(["a", "b", "c"], np.zeros(3), pos, operator_angles_rad=op)
    assert got["b"] == 1.0 and abs(got["c"] - (4.0 - 2 * math.pi)) < 1e-12
    # no positions: by id from the base angle
    assert assign_slot_angles(["y", "x"], np.zeros(3), base_angle_rad=0.5) == pytest.approx({"x": 0.5, "y": 0.5 - math.pi})
    with pytest.raises(SlotError):
        assign_slot_angles(["a"], np.zeros(3), operator_angles_rad={"a": float("nan")})


def test_supervisor_holds_slots_until_formation_changes():
    sup = FormationSupervisor("d0", FailsafeConfig())
    d1 = sup.update(inputs())
    moved = dict(inputs().positions_ned_m)
    moved["d1"] = (-6.0, 2.0, -8.0)
    d2 = sup.update(inputs(positions_ned_m=moved))
    assert d2.slot_angles_rad == d1.slot_angles_rad and d2.action is FailsafeAction.CONTINUE
    d3 = sup.update(inputs(teammates_last_seen_s={"d1": 99.9}, positions_ned_m=moved))
    assert d3.action is FailsafeAction.RESPACE and set(d3.slot_angles_rad) == {"d0", "d1"}
