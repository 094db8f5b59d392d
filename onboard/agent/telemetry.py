"""The autopilot link's typed telemetry record (units and frames in the names, like MAVSDK-Python's types).

:class:`Telemetry` is the latest of every telemetry stream the autopilot adapter
(:class:`onboard.agent.autopilot.MavsdkAutopilot`) subscribes to, as one frozen record: the adapter replaces it
(``dataclasses.replace``) on every sample, so a reader always holds a consistent snapshot. Positions are in the
flight's world NED frame (north / east about the configured origin, down about the ground the vehicle took off
from: heights are above the take-off point; the autopilot's local frame moved by its estimated offset), velocities in NED, the
attitude is the body-to-world quaternion (w, x, y, z). :meth:`Telemetry.vehicle_state` turns it into the
:class:`shared_msgs.VehicleState` the agent records and publishes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from shared_msgs import VehicleState

__all__ = ["Telemetry", "LANDED_STATES"]

#: MAVSDK's ``LandedState`` enum values -> the names used in :class:`Telemetry` and :class:`VehicleState`
LANDED_STATES = {0: "unknown", 1: "on_ground", 2: "in_air", 3: "taking_off", 4: "landing"}

_NAN = math.nan


@dataclass(frozen=True)
class Telemetry:
    """The autopilot's latest telemetry (one value per stream; defaults until a stream has spoken)."""

    #: world NED position (m); None until the autopilot's local origin is known in the world frame
    position_ned_m: tuple[float, float, float] | None = None
    velocity_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: attitude, body -> world NED, (w, x, y, z)
    q_world_body_wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    armed: bool = False
    in_air: bool = False
    #: one of :data:`LANDED_STATES`' names
    landed_state: str = "unknown"
    #: MAVSDK's ``FlightMode`` name (``"HOLD"``, ``"OFFBOARD"`` ...)
    flight_mode: str = "unknown"
    #: 0..1
    battery_remaining_frac: float = 1.0
    battery_voltage_v: float = 0.0
    latitude_deg: float = _NAN
    longitude_deg: float = _NAN
    altitude_amsl_m: float = _NAN
    gps_fix_type: int = 0
    gps_num_satellites: int = 0
    #: the receiver's position uncertainty (1 sigma, RAW_GPS); NaN when not reported
    horizontal_accuracy_m: float = _NAN
    vertical_accuracy_m: float = _NAN
    #: global position, home position and armable all OK
    health_ok: bool = False
    #: the parts of ``health_ok`` (MAVSDK ``Health``)
    global_position_ok: bool = False
    home_position_ok: bool = False
    armable: bool = False
    #: the camera gimbal (MAVSDK's gimbal plugin; 0 / NaN until one is discovered and reports): its MAVSDK id,
    #: roll and pitch relative to the horizon, yaw relative to the heading and to north (rad), report time (ns)
    gimbal_id: int = 0
    gimbal_roll_rad: float = _NAN
    gimbal_pitch_rad: float = _NAN
    gimbal_yaw_rad: float = _NAN
    gimbal_yaw_north_rad: float = _NAN
    gimbal_t_ns: int = 0

    @property
    def altitude_m(self) -> float:
        """Height above the ground the drone took off from (m, = -down of the world position, whose down is
        about the autopilot's home); 0 before the position is known."""
        return -self.position_ned_m[2] if self.position_ned_m is not None else 0.0

    def vehicle_state(self, drone_id: str, t_measurement_ns: int, seq: int) -> VehicleState:
        """This record as the :class:`VehicleState` message (needs the position). A non-finite attitude becomes
        the identity, non-finite geodetic values 0; the accuracies become ``position_cov_m2`` (h^2, h^2, v^2)
        when both are known, else the message's default."""
        if self.position_ned_m is None:
            raise ValueError("no world position yet")
        q = self.q_world_body_wxyz if all(math.isfinite(x) for x in self.q_world_body_wxyz) else (1.0, 0.0, 0.0, 0.0)
        extra = {}
        h, v = self.horizontal_accuracy_m, self.vertical_accuracy_m
        if math.isfinite(h) and math.isfinite(v):
            # the receiver's reported accuracy (GPS ~1 m, RTK ~cm); without it the message's default (1 m^2)
            extra["position_cov_m2"] = (h ** 2, h ** 2, v ** 2)
        return VehicleState(
            header=VehicleState.make_header(drone_id, t_measurement_ns, seq),
            position_ned_m=self.position_ned_m, velocity_ned_m_s=self.velocity_ned_m_s, q_world_body=q, **extra,
            latitude_deg=_finite(self.latitude_deg), longitude_deg=_finite(self.longitude_deg),
            altitude_amsl_m=_finite(self.altitude_amsl_m),
            gps_fix_type=self.gps_fix_type, gps_num_satellites=self.gps_num_satellites,
            battery_remaining_frac=self.battery_remaining_frac, battery_voltage_v=self.battery_voltage_v,
            flight_mode=self.flight_mode, armed=self.armed, landed_state=self.landed_state, health_ok=self.health_ok,
        )


def _finite(x: float) -> float:
    return float(x) if math.isfinite(x) else 0.0
