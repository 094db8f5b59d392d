"""Command/plan validation and the flight state machine (pure logic)."""

import math

import pytest

from shared_msgs import Command, OrbitPlan, now_ns
from onboard.config import SafetyConfig
from onboard.mission import Action, Mission, State, validate_command, validate_plan
from onboard.orbit import evenly_spaced_phases


def cmd(action="land", target="*", age_s=0.0, **kw):
    c = Command(header=Command.make_header("gcs"), command_id="c1", target=target, action=action, **kw)
    c.header.t_sent_ns = now_ns() - int(age_s * 1e9)
    return c


def plan(**kw):
    d = dict(plan_id="p1", center_ned_m=(0.0, 0.0, 0.0), radius_m=8.0, altitude_m=6.0, angular_speed_rad_s=0.2,
             phase_offset_rad=evenly_spaced_phases(["drone_1", "drone_2", "drone_3"]))
    d.update(kw)
    return OrbitPlan(header=OrbitPlan.make_header("gcs"), **d)


def test_command_validation():
    n = now_ns()
    assert validate_command(cmd(), "drone_1", n) is None
    assert validate_command(cmd(target="drone_1"), "drone_1", n) is None
    assert "wrong target" in validate_command(cmd(target="drone_2"), "drone_1", n)
    assert "stale" in validate_command(cmd(age_s=6.0), "drone_1", n)
    assert validate_command(cmd(age_s=6.0, max_age_s=10.0), "drone_1", n) is None
    assert "bad field params.altitude_m" in validate_command(cmd("takeoff", params={"altitude_m": -3.0}), "drone_1", n)
    assert "bad field max_age_s" in validate_command(cmd(max_age_s=0.0), "drone_1", n)


@pytest.mark.parametrize(
    "field,value,reason",
    [
        ("radius_m", 0.0, "bad field radius_m"),
        ("radius_m", -2.0, "bad field radius_m"),
        ("radius_m", float("nan"), "non-finite"),
        ("altitude_m", 0.5, "bad field altitude_m"),
        ("altitude_m", 500.0, "bad field altitude_m"),
        ("angular_speed_rad_s", 3.0, "slot speed"),
        ("angular_speed_rad_s", -0.1, "bad field angular_speed_rad_s"),
        ("phase_offset_rad", {"drone_2": 0.0}, "wrong target"),
        ("phase_offset_rad", {"drone_1": 0.0, "drone_2": 0.1}, "below min_separation_m"),
    ],
)
def test_plan_validation_refuses_bad_fields(field, value, reason):
    p = plan(**{field: value})
    r = validate_plan(p, "drone_1", SafetyConfig(), now_ns())
    assert r is not None and reason in r


def test_good_plan_accepted_and_stale_plan_refused():
    assert validate_plan(plan(), "drone_1", SafetyConfig(), now_ns()) is None
    p = plan()
    p.header.t_sent_ns -= int(60e9)
    assert "stale" in validate_plan(p, "drone_1", SafetyConfig(), now_ns())


def test_state_machine_nominal_flight():
    m = Mission()
    assert m.command("start").refused  # no plan, on the ground
    assert m.command("arm").action == Action.ARM
    assert m.command("takeoff").action == Action.TAKEOFF
    assert m.state == State.TAKEOFF
    assert m.vehicle(armed=True, in_air=True, at_altitude=False).state == State.TAKEOFF
    assert m.vehicle(armed=True, in_air=True, at_altitude=True).state == State.HOVER
    assert "no orbit plan" in m.command("start").refused
    m.set_plan(plan())
    assert m.command("start").action == Action.START_ORBIT
    assert m.command("pause").action == Action.PAUSE and m.state == State.PAUSED
    assert m.command("start").action == Action.START_ORBIT
    assert m.set_plan(plan(radius_m=9.0)).action == Action.START_ORBIT  # new plan in flight
    assert m.command("disarm").refused
    assert m.command("land").action == Action.LAND
    assert m.vehicle(armed=True, in_air=False, at_altitude=False).state == State.LANDED
    assert m.command("arm").action == Action.ARM


def test_failsafes_only_when_airborne_and_block_restart():
    m = Mission()
    assert m.trigger_failsafe("gcs lost", "land").action == Action.NONE  # on the ground: nothing
    m.command("takeoff")
    m.vehicle(True, True, True)
    m.set_plan(plan())
    m.command("start")
    t = m.trigger_failsafe("ground-station heartbeat lost", "land")
    assert t.action == Action.LAND and m.state == State.LANDING
    assert m.trigger_failsafe("again", "land").action == Action.NONE
    assert m.command("start").refused
    m2 = Mission()
    m2.command("takeoff"); m2.vehicle(True, True, True)
    assert m2.trigger_failsafe("battery", "return").action == Action.RETURN
    m3 = Mission()
    m3.command("takeoff"); m3.vehicle(True, True, True)
    assert m3.trigger_failsafe("shutdown", "hold").action == Action.HOLD


def test_closest_neighbour_ignores_stale_reports():
    from onboard.mission import closest_neighbour

    others = {"drone_2": ((3.0, 4.0, 0.0), 10.0), "drone_3": ((1.0, 0.0, 0.0), 5.0), "drone_4": ((0.0, 9.0, 0.0), 10.2)}
    assert closest_neighbour((0.0, 0.0, 0.0), others, now_s=10.5) == ("drone_2", 5.0)
    assert closest_neighbour((0.0, 0.0, 0.0), others, now_s=10.5, max_age_s=10.0) == ("drone_3", 1.0)
    assert closest_neighbour((0.0, 0.0, 0.0), others, now_s=30.0) is None


def test_offboard_lost_resume_follow_or_pause():
    def orbiting():
        m = Mission()
        m.command("takeoff"); m.vehicle(True, True, True); m.set_plan(plan()); m.command("start")
        return m

    assert orbiting().offboard_lost("HOLD", may_resume=True).action == Action.RESUME_OFFBOARD
    m = orbiting()
    assert m.offboard_lost("HOLD", may_resume=False).state == State.PAUSED  # resume budget spent
    m = orbiting()
    assert m.offboard_lost("POSCTL", may_resume=True).state == State.PAUSED  # a pilot took over
    assert m.command("start").action == Action.START_ORBIT  # the operator resumes
    assert orbiting().offboard_lost("LAND", True).state == State.LANDING
    assert orbiting().offboard_lost("RETURN_TO_LAUNCH", True).action == Action.RESUME_OFFBOARD  # our stall's RTL
    assert orbiting().offboard_lost("RETURN_TO_LAUNCH", False).state == State.RETURNING
    assert orbiting().offboard_lost("LAND", False).state == State.LANDING
    idle = Mission()
    assert idle.offboard_lost("HOLD", True).action == Action.NONE


def test_arm_waits_for_the_vehicle_before_following_a_disarm():
    m = Mission()
    m.command("arm")
    assert m.vehicle(armed=False, in_air=False, at_altitude=False).state == State.ARMED  # not armed yet
    m.vehicle(armed=True, in_air=False, at_altitude=False)
    assert m.vehicle(armed=False, in_air=False, at_altitude=False).state == State.IDLE  # auto-disarm

