"""The autopilot link's typed telemetry record: defaults, conversion to VehicleState, and the MAVSDK adapter
keeping it (no autopilot needed: the adapter's stream callbacks get MAVSDK-shaped values)."""

from __future__ import annotations

import asyncio
import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest

from onboard.agent.autopilot import MavsdkAutopilot
from onboard.agent.telemetry import Telemetry
from skycap.frames import geodetic_to_ned


def test_record_is_frozen_with_defaults_until_streams_speak():
    t = Telemetry()
    assert t.position_ned_m is None and t.altitude_m == 0.0 and not t.armed and not t.health_ok
    assert t.q_world_body_wxyz == (1.0, 0.0, 0.0, 0.0) and t.battery_remaining_frac == 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        t.armed = True  # type: ignore[misc]
    assert dataclasses.replace(t, position_ned_m=(1.0, 2.0, -7.5)).altitude_m == 7.5


def test_vehicle_state_conversion():
    t = Telemetry(position_ned_m=(1.0, 2.0, -3.0), velocity_ned_m_s=(0.5, 0.0, -0.1),
                  q_world_body_wxyz=(0.0, 0.0, 0.0, 1.0), armed=True, in_air=True, landed_state="in_air",
                  flight_mode="OFFBOARD", battery_remaining_frac=0.7, battery_voltage_v=15.2, latitude_deg=47.4,
                  longitude_deg=8.5, altitude_amsl_m=491.0, gps_fix_type=3, gps_num_satellites=12,
                  horizontal_accuracy_m=0.5, vertical_accuracy_m=0.8, health_ok=True)
    st = t.vehicle_state("drone_2", 123_000, 7)
    assert st.header.sender_id == "drone_2" and st.header.t_measurement_ns == 123_000 and st.header.seq == 7
    assert st.position_ned_m == (1.0, 2.0, -3.0) and st.velocity_ned_m_s == (0.5, 0.0, -0.1)
    assert st.q_world_body == (0.0, 0.0, 0.0, 1.0)
    assert st.position_cov_m2 == (0.5 ** 2, 0.5 ** 2, 0.8 ** 2)  # accuracies (1 sigma, m) -> variances (m^2)
    assert (st.latitude_deg, st.longitude_deg, st.altitude_amsl_m) == (47.4, 8.5, 491.0)
    assert (st.gps_fix_type, st.gps_num_satellites) == (3, 12)
    assert (st.battery_remaining_frac, st.battery_voltage_v) == (0.7, 15.2)
    assert (st.flight_mode, st.armed, st.landed_state, st.health_ok) == ("OFFBOARD", True, "in_air", True)
    # non-finite attitude -> identity; unknown geodetic -> 0; no accuracy -> the message's default covariance
    bare = Telemetry(position_ned_m=(0.0, 0.0, 0.0), q_world_body_wxyz=(math.nan, 0.0, 0.0, 0.0),
                     horizontal_accuracy_m=0.5).vehicle_state("d", 1, 1)
    assert bare.q_world_body == (1.0, 0.0, 0.0, 0.0) and bare.latitude_deg == 0.0 and bare.altitude_amsl_m == 0.0
    assert bare.position_cov_m2 == (1.0, 1.0, 1.0)
    with pytest.raises(ValueError):
        Telemetry().vehicle_state("d", 1, 1)


class _Stream:
    """A MAVSDK telemetry subscription yielding the given values once."""

    def __init__(self, name: str, values):
        self.__name__ = name
        self.values = values

    async def __call__(self):
        for v in self.values:
            yield v


def test_adapter_keeps_the_record_and_reports_world_states():
    async def main():
        origin = (47.397742, 8.545594, 488.0)
        states = []
        ap = MavsdkAutopilot("drone_1", on_state=states.append, origin=origin, offset_samples=2)
        lat, lon, alt = 47.397842, 8.545694, 489.0  # ~11 m north, ~7.5 m east, 1 m up of the origin
        world = geodetic_to_ned(lat, lon, alt, *origin)
        world[2] = 0.0  # heights are above the ground the vehicle stands on, not above the origin's 488 m
        ned = lambda n, e, d: SimpleNamespace(north_m=n, east_m=e, down_m=d)
        posvel = [SimpleNamespace(position=ned(1.0, 2.0, -0.5), velocity=SimpleNamespace(north_m_s=0.1, east_m_s=0.0, down_m_s=0.0))
                  for _ in range(3)]
        S = SimpleNamespace
        tel = SimpleNamespace(
            subscribe_attitude_quaternion=_Stream("att", [S(w=0.0, x=0.0, y=0.0, z=1.0)]),
            subscribe_armed=_Stream("armed", [True]), subscribe_in_air=_Stream("in_air", [True]),
            subscribe_landed_state=_Stream("landed", [2]), subscribe_flight_mode=_Stream("mode", [S(name="HOLD")]),
            subscribe_battery=_Stream("battery", [S(remaining_percent=64.0, voltage_v=15.1)]),
            subscribe_position=_Stream("position", [S(latitude_deg=lat, longitude_deg=lon, absolute_altitude_m=alt)]),
            subscribe_gps_info=_Stream("gps", [S(fix_type=3, num_satellites=11)]),
            subscribe_health=_Stream("health", [S(is_global_position_ok=True, is_home_position_ok=True, is_armable=True)]),
            subscribe_raw_gps=_Stream("raw_gps", [S(horizontal_uncertainty_m=0.4, vertical_uncertainty_m=120.0)]),
            subscribe_position_velocity_ned=_Stream("posvel", []),
        )

        async def rate(_hz):
            return None

        for name in ("set_rate_position_velocity_ned", "set_rate_attitude_quaternion", "set_rate_position",
                     "set_rate_battery", "set_rate_in_air", "set_rate_landed_state"):
            setattr(tel, name, rate)
        ap.tel = tel
        await ap.start_telemetry(10.0)
        await asyncio.sleep(0.05)  # the stream tasks run
        T = ap.telemetry
        assert isinstance(T, Telemetry)
        assert T.q_world_body_wxyz == (0.0, 0.0, 0.0, 1.0) and T.armed and T.in_air and T.landed_state == "in_air"
        assert T.flight_mode == "HOLD" and T.battery_remaining_frac == 0.64 and T.battery_voltage_v == 15.1
        assert (T.gps_fix_type, T.gps_num_satellites, T.health_ok) == (3, 11, True)
        assert T.horizontal_accuracy_m == 0.4 and math.isnan(T.vertical_accuracy_m)  # > 90 m: not a report
        assert T.position_ned_m is None
        ap.telemetry = dataclasses.replace(ap.telemetry, landed_state="on_ground", in_air=False)
        for v in posvel:  # two samples place the local origin; from the second on they are reported
            ap._on_posvel(v)
        offset = world - np.array([1.0, 2.0, -0.5])
        np.testing.assert_allclose(ap.local_to_world_ned_m, offset)
        np.testing.assert_allclose(ap.telemetry.position_ned_m, world)
        assert ap.ground_local_down_m == pytest.approx(-0.5)
        # in the air: the ground level is frozen, the height is above it
        ap.telemetry = dataclasses.replace(ap.telemetry, landed_state="in_air", in_air=True)
        ap._on_posvel(SimpleNamespace(position=ned(1.0, 2.0, -3.5), velocity=posvel[0].velocity))
        assert ap.telemetry.position_ned_m[2] == pytest.approx(-3.0) and ap.ground_local_down_m == pytest.approx(-0.5)
        ap._on_posvel(posvel[0])
        assert ap.telemetry.velocity_ned_m_s == (0.1, 0.0, 0.0)
        assert len(states) == 4 and states[-1] is ap.last_state and states[-1].header.seq == 4
        np.testing.assert_allclose(states[-1].position_ned_m, world)
        assert states[-1].position_cov_m2 == (1.0, 1.0, 1.0)  # no vertical accuracy: the default
        assert states[-1].battery_remaining_frac == 0.64 and states[-1].flight_mode == "HOLD"
        await ap.close()

    asyncio.run(main())
