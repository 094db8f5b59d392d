"""PX4 custom-mode encoding (px4_custom_mode.h) as MAVSDK decodes it."""

import pytest

from simulator.vehicle.px4_modes import (
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
    MAV_MODE_FLAG_SAFETY_ARMED,
    AutoSubMode,
    FlightMode,
    MainMode,
    decode_custom_mode,
    encode_custom_mode,
    flight_mode_from_px4,
    heartbeat_base_mode,
)


def test_known_px4_custom_mode_words():
    # values as PX4 sends them (QGC/MAVSDK decode these): Hold = AUTO/LOITER, Offboard, RTL, Land, Takeoff
    assert encode_custom_mode(MainMode.AUTO, AutoSubMode.LOITER) == 0x03040000 == 50593792
    assert encode_custom_mode(MainMode.OFFBOARD) == 0x00060000 == 393216
    assert encode_custom_mode(MainMode.AUTO, AutoSubMode.RTL) == 84148224
    assert encode_custom_mode(MainMode.AUTO, AutoSubMode.LAND) == 100925440
    assert encode_custom_mode(MainMode.AUTO, AutoSubMode.TAKEOFF) == 33816576
    assert encode_custom_mode(MainMode.POSCTL) == 196608


@pytest.mark.parametrize("mode", list(FlightMode))
def test_encode_decode_roundtrip(mode):
    word = encode_custom_mode(mode.main_mode, mode.sub_mode)
    assert decode_custom_mode(word) == (mode.main_mode, mode.sub_mode)
    assert flight_mode_from_px4(*decode_custom_mode(word)) is mode


def test_non_auto_modes_ignore_sub_mode_and_unknown_is_none():
    assert flight_mode_from_px4(MainMode.OFFBOARD, 3) is FlightMode.OFFBOARD
    assert flight_mode_from_px4(MainMode.AUTO, AutoSubMode.FOLLOW_TARGET) is None
    assert flight_mode_from_px4(MainMode.ACRO, 0) is None
    with pytest.raises(ValueError):
        encode_custom_mode(300, 0)


def test_base_mode_flags():
    armed = heartbeat_base_mode(FlightMode.HOLD, armed=True)
    assert armed & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and armed & MAV_MODE_FLAG_SAFETY_ARMED
    assert not heartbeat_base_mode(FlightMode.OFFBOARD, armed=False) & MAV_MODE_FLAG_SAFETY_ARMED
