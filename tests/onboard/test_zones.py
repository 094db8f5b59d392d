"""The plan's geofence and keep-out zones on board (:mod:`onboard.zones`): the agent's plan check refuses a plan
that leaves the fence or enters a zone, with the reason; the setpoint clamp keeps every streamed setpoint out of
the zones and inside the fence; the formation MPC built for a fenced plan keeps its plan out of a zone."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onboard.config import AgentConfig, SafetyConfig
from onboard.mission import validate_plan
from onboard.orbit import evenly_spaced_phases
from onboard.zones import clamp_setpoint, fence_polygon_ne, plan_zone_violation
from shared_msgs import GeofenceZone, KeepOutZone, OrbitPlan, decode, encode, now_ns

IDS = ["drone_1", "drone_2", "drone_3"]


def plan(**kw) -> OrbitPlan:
    d = dict(plan_id="p1", center_ned_m=(0.0, 0.0, 0.0), radius_m=8.0, altitude_m=6.0, angular_speed_rad_s=0.2,
             phase_offset_rad=evenly_spaced_phases(IDS), geofence=GeofenceZone(radius_m=30.0, max_altitude_m=20.0))
    d.update(kw)
    return OrbitPlan(header=OrbitPlan.make_header("gcs"), **d)


def test_a_plan_inside_the_fence_and_clear_of_the_zones_is_accepted():
    p = plan(keepout_zones=[KeepOutZone(name="house", north_m=20.0, east_m=0.0, radius_m=5.0)])
    assert all(plan_zone_violation(p, d) is None for d in IDS)
    assert validate_plan(p, "drone_1", SafetyConfig(), now_ns(), mode="orbit") is None
    assert plan_zone_violation(plan(geofence=None), "drone_1") is None  # a version-1 plan: nothing to check


@pytest.mark.parametrize("kw, want", [
    (dict(center_ned_m=(25.0, 0.0, 0.0)), "leaves the fence"),
    (dict(altitude_m=25.0), "outside the fence's band"),
    (dict(keepout_zones=[KeepOutZone(name="house", north_m=8.0, east_m=1.0, radius_m=2.0)]),
     "keep-out zone 'house': the orbit"),
    (dict(keepout_zones=[KeepOutZone(north_m=0.0, east_m=0.0, radius_m=-1.0)]), "radius_m > 0"),
    (dict(geofence=GeofenceZone(radius_m=30.0, min_altitude_m=10.0, max_altitude_m=5.0)), "min_altitude_m"),
])
def test_the_agent_refuses_an_orbit_that_leaves_the_fence_or_crosses_a_zone(kw, want):
    why = validate_plan(plan(**kw), "drone_1", SafetyConfig(), now_ns(), mode="orbit")
    assert why is not None and want in why, why


def test_a_tracking_formation_is_checked_at_each_drones_slot_around_the_start_guess():
    # slot of drone_1 is north of the start guess (phase 0): a zone there refuses drone_1 only
    zone = KeepOutZone(name="tree", north_m=13.0, east_m=5.0, radius_m=2.0)
    p = plan(mode="track", angular_speed_rad_s=0.0, center_ned_m=(5.0, 5.0, 0.0), keepout_zones=[zone])
    assert "tree': drone_1's slot" in plan_zone_violation(p, "drone_1")
    assert plan_zone_violation(p, "drone_2") is None and plan_zone_violation(p, "drone_3") is None
    # a slot outside the fence (the start guess near the fence's edge)
    p = plan(mode="track", angular_speed_rad_s=0.0, center_ned_m=(25.0, 0.0, 0.0))
    assert "drone_1's slot (33.0, 0.0 m) is outside the fence" in plan_zone_violation(p, "drone_1")
    assert plan_zone_violation(p, "drone_2") is None  # its slot is inside


def test_the_agent_refuses_a_plan_of_the_other_mode_and_flies_an_unsaid_one():
    track = plan(mode="track", angular_speed_rad_s=0.0)
    why = validate_plan(track, "drone_1", SafetyConfig(), now_ns(), mode="orbit")
    assert "wrong mode: the plan is a tracking formation" in why and "mode 'orbit'" in why
    assert validate_plan(track, "drone_1", SafetyConfig(), now_ns(), mode="track") is None
    assert "wrong mode" in validate_plan(plan(mode="orbit"), "drone_1", SafetyConfig(), now_ns(), mode="track")
    assert validate_plan(plan(mode=""), "drone_1", SafetyConfig(), now_ns(), mode="track") is None


def test_the_zones_travel_with_the_plan():
    p = plan(keepout_zones=[KeepOutZone(name="house", north_m=20.0, east_m=0.0, radius_m=5.0)], mode="track")
    q = decode(encode(p), OrbitPlan)
    assert q.geofence == p.geofence and q.keepout_zones == p.keepout_zones and q.mode == "track"


def test_the_setpoint_clamp_keeps_setpoints_out_of_zones_and_inside_the_fence():
    fence = GeofenceZone(radius_m=30.0, max_altitude_m=20.0)
    zone = KeepOutZone(name="house", north_m=10.0, east_m=0.0, radius_m=3.0)
    # fine: unchanged
    p, v, what = clamp_setpoint((0.0, 0.0, -6.0), (1.0, 0.0, 0.0), fence, [zone])
    assert what == [] and list(p) == [0.0, 0.0, -6.0] and list(v) == [1.0, 0.0, 0.0]
    # inside the zone, flying into it: moved to its edge + margin, the inward velocity removed
    p, v, what = clamp_setpoint((8.0, 0.5, -6.0), (2.0, 1.0, 0.0), fence, [zone], margin_m=0.5)
    assert what == ["keep-out zone 'house'"]
    assert math.hypot(p[0] - 10.0, p[1]) == pytest.approx(3.5)
    n = np.array([p[0] - 10.0, p[1]]) / 3.5
    assert float(v[:2] @ n) >= -1e-9 and p[2] == -6.0
    # outside the fence and above its ceiling
    p, v, what = clamp_setpoint((40.0, 0.0, -25.0), (3.0, 1.0, -1.0), fence, [], margin_m=0.5)
    assert what == ["geofence", "geofence ceiling"]
    assert p[0] == pytest.approx(29.5) and p[1] == pytest.approx(0.0) and p[2] == -20.0
    assert v[0] == pytest.approx(0.0) and v[1] == pytest.approx(1.0) and v[2] == 0.0


def test_the_fence_polygon_is_convex_and_inside_the_circle():
    f = GeofenceZone(center_ne_m=(5.0, -3.0), radius_m=20.0)
    poly = np.array(fence_polygon_ne(f))
    assert len(poly) == 16
    assert np.allclose(np.hypot(poly[:, 0] - 5.0, poly[:, 1] + 3.0), 20.0)


def test_the_track_mode_mpc_gets_the_fence_and_zones_and_plans_around_a_zone():
    from onboard.agent.formation import mpc_config
    from onboard.formation.mpc import FormationMPC

    zone = KeepOutZone(name="tree", north_m=8.0, east_m=0.0, radius_m=2.0)
    p = plan(mode="track", angular_speed_rad_s=0.0, keepout_zones=[zone], phase_offset_rad={"drone_1": 0.0})
    cfg = AgentConfig(drone_id="drone_1", mode="track")
    mc = mpc_config(cfg, p)
    assert len(mc.geofence_ne_m) == 16 and mc.obstacles[0].radius_m == 2.0 and mc.max_altitude_m <= 20.0
    mpc = FormationMPC("drone_1", mc)
    # the drone west of the zone; its slot (8, 0) lies inside the zone: every planned position stays out of it
    pos, vel = np.array([4.0, -6.0, -6.0]), np.zeros(3)
    t_ns = 1_000_000_000_000
    for k in range(10):
        r = mpc.step(t_ns + k * 100_000_000, pos, vel, np.array([0.0, 0.0, -0.9]), np.zeros(3), 0.0, {}, 0.0)
        d = np.hypot(r.plan.positions_ned_m[1:, 0] - 8.0, r.plan.positions_ned_m[1:, 1])
        assert r.ok and d.min() >= 2.0 + mc.obstacle_margin_m - 0.05, (k, d.min(), r.status)
        pos, vel = r.setpoint_position_ned_m, r.setpoint_velocity_ned_m_s
