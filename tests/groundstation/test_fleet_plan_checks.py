"""The fleet client checks a plan before sending it, with the agents' own rules (pure: no network)."""

import math

import msgspec
import pytest

from groundstation.fleet import FleetError, check_plan, make_orbit_plan
from onboard.config import SafetyConfig

IDS = ["drone_1", "drone_2", "drone_3"]


@pytest.mark.parametrize("kw, match", [
    (dict(radius_m=0.0), "radius_m=0.0: must be > 0"),
    (dict(altitude_m=math.inf), "non-finite"),
    (dict(altitude_m=80.0), "altitude_m=80.0: outside the band 2.0..60.0"),
    (dict(radius_m=1.5, min_separation_m=3.0), "slots 2.60 m apart, below min_separation_m=3.0"),
    (dict(angular_speed_rad_s=2.0), "slot speed 16.0 m/s above the limit"),
    (dict(angular_speed_rad_s=-0.1), "must be >= 0 \\(use direction\\)"),
    (dict(direction=0), "direction=0: use 1 or -1"),
    (dict(gimbal_pitch_rad=-2.0), "gimbal_pitch_rad"),
])
def test_a_plan_the_drones_would_refuse_is_not_made(kw, match):
    with pytest.raises(FleetError, match=match):
        make_orbit_plan(IDS, (0.0, 0.0, 0.0), **kw)


def test_drone_lists_and_the_safety_band():
    with pytest.raises(FleetError, match="drone_2 named more than once"):
        make_orbit_plan(["drone_1", "drone_2", "drone_2"])
    with pytest.raises(FleetError, match="at least one drone"):
        make_orbit_plan([])
    with pytest.raises(FleetError, match="'drone 4'"):
        make_orbit_plan(["drone 4"])
    plan = make_orbit_plan(IDS, (0.0, 0.0, 0.0), radius_m=8.0, altitude_m=6.0)
    check_plan(plan)  # fine with the default limits
    with pytest.raises(FleetError, match="outside the band 10.0..60.0"):
        check_plan(plan, SafetyConfig(min_altitude_m=10.0))
    with pytest.raises(FleetError, match="no drone slots"):
        check_plan(msgspec.structs.replace(plan, phase_offset_rad={}))


def test_the_fence_and_zones_travel_with_the_plan_and_a_plan_entering_them_is_not_made():
    from shared_msgs import GeofenceZone, KeepOutZone

    fence, shed = GeofenceZone(radius_m=30.0), KeepOutZone(name="shed", north_m=16.0, east_m=-16.0, radius_m=3.0)
    plan = make_orbit_plan(IDS, radius_m=8.0, mode="orbit", geofence=fence, keepout_zones=[shed])
    assert plan.geofence == fence and plan.keepout_zones == [shed] and plan.mode == "orbit"
    with pytest.raises(FleetError, match="keep-out zone 'shed': the orbit"):
        make_orbit_plan(IDS, (10.0, -10.0, 0.0), radius_m=8.0, geofence=fence, keepout_zones=[shed])
    with pytest.raises(FleetError, match="leaves the fence"):
        make_orbit_plan(IDS, (25.0, 0.0, 0.0), radius_m=8.0, geofence=fence)
    # a tracking formation: each drone's slot around the start guess (drone_1's, north of it, is in the shed)
    with pytest.raises(FleetError, match="drone_1's slot"):
        make_orbit_plan(IDS, (8.0, -16.0, 0.0), 8.0, 6.0, 0.0, mode="track", geofence=fence, keepout_zones=[shed])
    with pytest.raises(FleetError, match="plan mode 'chase'"):
        make_orbit_plan(IDS, mode="chase")


class _Sub:
    def close(self):
        pass


class _Bus:
    """Enough of a transport for the fleet model's plan checks (nothing arrives; sent plans are kept)."""

    secure = False

    def __init__(self):
        self.sent = []

    def subscribe(self, *a, **k):
        return _Sub()

    def watch_presence(self, *a, **k):
        return _Sub()

    def declare_alive(self, *a, **k):
        pass

    def publish(self, key, msg, latch=False):
        self.sent.append((key, msg))


def test_the_plan_form_validates_a_tracking_formation_and_the_zones_before_sending():
    from groundstation.app.config import GsConfig, KeepOutZoneConfig
    from groundstation.app.model import FleetModel, PlanForm
    from groundstation.fleet import FleetClient

    cfg = GsConfig(event_log="", keepout_zones=[KeepOutZoneConfig("shed", 16.0, -16.0, 3.0)]).validate()
    bus = _Bus()
    client = FleetClient("f", bus, heartbeat_hz=0)
    model = FleetModel(client, cfg)
    two = ["drone_1", "drone_2"]
    cases = [
        (PlanForm(mode="track", drones=two, radius_m=-1), "stand-off radius must be positive"),
        (PlanForm(mode="track", drones=two, altitude_m=40), "outside the fence's band"),
        (PlanForm(mode="track", drones=two, radius_m=1.0), "separation not feasible"),
        (PlanForm(mode="track", drones=["drone_1", "drone_1"]), "named more than once"),
        (PlanForm(mode="track", drones=two, center_north_m=40.0), "start guess (40, 0 m) is outside the fence"),
        (PlanForm(mode="track", drones=two, center_north_m=8.0, center_east_m=-16.0), "keep-out zone 'shed': drone_1's slot"),
        (PlanForm(mode="orbit", drones=two, center_north_m=10.0, center_east_m=-10.0), "keep-out zone 'shed': the orbit"),
        (PlanForm(mode="orbit", drones=two, center_north_m=25.0), "leaves the fence"),
    ]
    for form, want in cases:
        plan, why = model.validate_plan(form)
        assert plan is None and want in why, (form, why)
        run, why2 = model.send_plan(form)
        assert run is None and want in why2
    assert not [m for _, m in bus.sent if type(m).__name__ == "OrbitPlan"]  # nothing was sent
    # a good tracking formation: speed unused (0 rad/s), the fence and the zone go with it
    run, why = model.send_plan(PlanForm(mode="track", drones=two, center_north_m=1.5, center_east_m=-1.0,
                                        speed_m_s=-5.0))
    assert run is not None and why == "", why
    plan = [m for _, m in bus.sent if type(m).__name__ == "OrbitPlan"][-1]
    assert plan.mode == "track" and plan.angular_speed_rad_s == 0.0 and plan.center_ned_m == (1.5, -1.0, 0.0)
    assert plan.geofence.radius_m == 30.0 and [z.name for z in plan.keepout_zones] == ["shed"]
    model.close()
    client.close()
