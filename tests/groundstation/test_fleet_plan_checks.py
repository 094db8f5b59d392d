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
