"""The agent's one setpoint type and the setpoint-source protocol: pure logic over numpy, no I/O.

A :class:`Setpoint` is what the onboard agent streams to its autopilot each control tick (MAVSDK offboard
position + velocity + acceleration feed-forward + yaw, in the flight's world NED frame, plus the camera
gimbal's pitch). Every :class:`SetpointSource` makes them: :class:`HoldSource` (pause),
:class:`onboard.orbit.OrbitController` (orbit mode), :class:`onboard.formation.source.FormationSource`
(track mode).

The built-in simulator's flight controller has its own input, :class:`simulator.vehicle.controller.TrajectorySetpoint`
(PX4's ``trajectory_setpoint``: the vehicle's local frame, NaN = axis not controlled, yaw rate, speed limits,
attitude mode): a different thing, reached over MAVLink, never this class.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

__all__ = ["Setpoint", "SetpointSource", "HoldSource"]


@dataclass
class Setpoint:
    """One offboard setpoint (NED world frame).

    position_ned_m: (3,) metres; velocity_ned_m_s: (3,) feed-forward; yaw_rad: heading (0 = north,
    positive = east); gimbal_pitch_rad: camera pitch (negative = down) or None for "leave it".
    """

    position_ned_m: np.ndarray
    velocity_ned_m_s: np.ndarray
    yaw_rad: float
    gimbal_pitch_rad: float | None = None
    acceleration_ned_m_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))


class SetpointSource(Protocol):
    """What the agent's control loop asks for a setpoint each tick.

    ``update(t_s, position_ned_m, velocity_ned_m_s, yaw_rad)`` gets the time (s, same clock as the
    plan's start time) and the vehicle's estimate, and returns the :class:`Setpoint` to stream.
    """

    def update(self, t_s: float, position_ned_m: np.ndarray, velocity_ned_m_s: np.ndarray, yaw_rad: float) -> Setpoint: ...


class HoldSource:
    """Hold a fixed point and heading (pause, or waiting for a plan while in offboard)."""

    def __init__(self, position_ned_m, yaw_rad: float):
        self.position_ned_m = np.asarray(position_ned_m, dtype=float).copy()
        self.yaw_rad = float(yaw_rad)

    def update(self, t_s, position_ned_m, velocity_ned_m_s, yaw_rad) -> Setpoint:
        return Setpoint(self.position_ned_m.copy(), np.zeros(3), self.yaw_rad)
