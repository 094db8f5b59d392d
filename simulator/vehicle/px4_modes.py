"""PX4 flight modes as MAVLink carries them (PX4 ``src/modules/commander/px4_custom_mode.h``).

``HEARTBEAT.custom_mode`` is a uint32 whose bytes are ``[reserved, reserved, main_mode, sub_mode]``
(little endian), i.e. ``custom_mode = main_mode << 16 | sub_mode << 24``; it is only meaningful when
``base_mode`` has ``MAV_MODE_FLAG_CUSTOM_MODE_ENABLED``. MAVSDK decodes it the same way
(``flight_mode.cpp``): e.g. AUTO/LOITER -> Hold, AUTO/RTL -> ReturnToLaunch, OFFBOARD -> Offboard.
"""

from __future__ import annotations

import enum

# MAVLink base_mode flags (common.xml MAV_MODE_FLAG)
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_MODE_FLAG_TEST_ENABLED = 2
MAV_MODE_FLAG_AUTO_ENABLED = 4
MAV_MODE_FLAG_GUIDED_ENABLED = 8
MAV_MODE_FLAG_STABILIZE_ENABLED = 16
MAV_MODE_FLAG_HIL_ENABLED = 32
MAV_MODE_FLAG_MANUAL_INPUT_ENABLED = 64
MAV_MODE_FLAG_SAFETY_ARMED = 128


class MainMode(enum.IntEnum):
    """PX4_CUSTOM_MAIN_MODE."""

    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7
    RATTITUDE_LEGACY = 8
    SIMPLE = 9
    TERMINATION = 10


class AutoSubMode(enum.IntEnum):
    """PX4_CUSTOM_SUB_MODE_AUTO (only with MainMode.AUTO)."""

    READY = 1
    TAKEOFF = 2
    LOITER = 3
    MISSION = 4
    RTL = 5
    LAND = 6
    RESERVED_DO_NOT_USE = 7
    FOLLOW_TARGET = 8
    PRECLAND = 9
    VTOL_TAKEOFF = 10


class FlightMode(enum.Enum):
    """The modes this simulator flies, each with its PX4 (main, sub) encoding; names as MAVSDK shows them."""

    MANUAL = (MainMode.MANUAL, 0)
    ALTCTL = (MainMode.ALTCTL, 0)
    POSCTL = (MainMode.POSCTL, 0)
    STABILIZED = (MainMode.STABILIZED, 0)
    READY = (MainMode.AUTO, AutoSubMode.READY)
    TAKEOFF = (MainMode.AUTO, AutoSubMode.TAKEOFF)
    HOLD = (MainMode.AUTO, AutoSubMode.LOITER)
    MISSION = (MainMode.AUTO, AutoSubMode.MISSION)
    RETURN = (MainMode.AUTO, AutoSubMode.RTL)
    LAND = (MainMode.AUTO, AutoSubMode.LAND)
    OFFBOARD = (MainMode.OFFBOARD, 0)

    @property
    def main_mode(self) -> int:
        return int(self.value[0])

    @property
    def sub_mode(self) -> int:
        return int(self.value[1])


def encode_custom_mode(main_mode: int, sub_mode: int = 0) -> int:
    """PX4 ``custom_mode`` uint32 from (main, sub)."""
    if not 0 <= main_mode <= 255 or not 0 <= sub_mode <= 255:
        raise ValueError(f"PX4 main/sub mode must be bytes, got main={main_mode} sub={sub_mode}")
    return (int(main_mode) << 16) | (int(sub_mode) << 24)


def decode_custom_mode(custom_mode: int) -> tuple[int, int]:
    """(main_mode, sub_mode) from a PX4 ``custom_mode`` uint32."""
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


def flight_mode_from_px4(main_mode: int, sub_mode: int) -> FlightMode | None:
    """The :class:`FlightMode` for a PX4 (main, sub) pair, or None if this simulator does not fly it.

    Non-AUTO main modes ignore the sub mode (as PX4 does).
    """
    for fm in FlightMode:
        if fm.main_mode == main_mode and (main_mode != MainMode.AUTO or fm.sub_mode == sub_mode):
            return fm
    return None


def heartbeat_base_mode(mode: FlightMode, armed: bool) -> int:
    """``HEARTBEAT.base_mode`` as PX4 fills it (``mavlink_messages.cpp`` get_mavlink_navigation_mode)."""
    flags = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    if armed:
        flags |= MAV_MODE_FLAG_SAFETY_ARMED
    if mode in (FlightMode.MANUAL, FlightMode.ALTCTL, FlightMode.POSCTL, FlightMode.STABILIZED):
        flags |= MAV_MODE_FLAG_MANUAL_INPUT_ENABLED | MAV_MODE_FLAG_STABILIZE_ENABLED
    else:
        flags |= MAV_MODE_FLAG_AUTO_ENABLED | MAV_MODE_FLAG_GUIDED_ENABLED | MAV_MODE_FLAG_STABILIZE_ENABLED
    return flags
