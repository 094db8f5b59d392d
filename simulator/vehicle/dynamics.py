"""Multirotor rigid-body dynamics at the level a position controller sees (no motors, no aerodynamics tables).

Model (NED world, FRD body; specific forces, i.e. per unit mass):

* the vehicle produces thrust ``thrust_m_s2`` along ``-z_body``; ``z_body`` (third column of
  ``R_world_body``) follows the commanded thrust direction with a first-order lag
  (``attitude_time_constant_s``, a stand-in for the attitude + rate loops), its tilt from vertical is
  limited to ``max_tilt_deg``; yaw follows a yaw-rate command limited to ``max_yaw_rate_deg_s``;
* ``accel = R_world_body @ [0, 0, -thrust] + g + drag * (wind - velocity)``;
* flat ground at ``down = ground_down_m``: the vehicle rests on it (contact), takes off when the
  thrust exceeds gravity.

All state is numpy; :meth:`MultirotorDynamics.step` is pure (no I/O, no clock), so tests can run it
faster than real time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

GRAVITY_M_S2 = 9.80665
G_NED = np.array([0.0, 0.0, GRAVITY_M_S2])


def R_from_body_z_and_yaw(body_z: np.ndarray, yaw_rad: float) -> np.ndarray:
    """``R_world_body`` (3,3) whose third column is ``body_z`` (3, unit) and whose heading is ``yaw_rad``.

    Same construction as PX4 ``ControlMath::bodyzToAttitude``.
    """
    zx, zy, zz = float(body_z[0]), float(body_z[1]), float(body_z[2])
    yx, yy = -math.sin(yaw_rad), math.cos(yaw_rad)  # y_c = (yx, yy, 0)
    # body_x = y_c x body_z (explicit: np.cross is slow on 3-vectors)
    bx, by, bz = yy * zz, -yx * zz, yx * zy - yy * zx
    if zz < 0.0:  # upside down: keep the nose pointing the same way
        bx, by, bz = -bx, -by, -bz
    nx = math.sqrt(bx * bx + by * by + bz * bz)
    if nx < 1e-9:  # body_z horizontal and along y_c (degenerate) -> pick any x
        bx, by, bz = 0.0, 0.0, 1.0
    else:
        bx, by, bz = bx / nx, by / nx, bz / nx
    # body_y = body_z x body_x
    return np.array(
        [
            [bx, zy * bz - zz * by, zx],
            [by, zz * bx - zx * bz, zy],
            [bz, zx * by - zy * bx, zz],
        ]
    )


def limit_tilt(body_z: np.ndarray, max_tilt_rad: float) -> np.ndarray:
    """Clamp the angle between ``body_z`` (3, unit) and straight down to ``max_tilt_rad``; returns a unit vector."""
    cos_tilt = body_z[2]
    if cos_tilt >= math.cos(max_tilt_rad):
        return body_z
    horiz = body_z[:2]
    nh = math.hypot(horiz[0], horiz[1])
    if nh < 1e-9:
        return np.array([0.0, 0.0, 1.0])
    s, c = math.sin(max_tilt_rad), math.cos(max_tilt_rad)
    return np.array([horiz[0] / nh * s, horiz[1] / nh * s, c])


@dataclass
class DynamicsLimits:
    """Physical envelope of the airframe (the controller has its own, tighter, limits)."""

    max_tilt_rad: float = math.radians(35.0)
    max_yaw_rate_rad_s: float = math.radians(60.0)
    attitude_time_constant_s: float = 0.08
    thrust_time_constant_s: float = 0.04
    max_thrust_m_s2: float = 2.0 * GRAVITY_M_S2
    drag_per_mass_1_s: float = 0.25


@dataclass
class RigidBodyState:
    """True kinematic state of one vehicle. Shapes: position/velocity (3,), R_world_body (3,3)."""

    position_ned_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    velocity_ned_m_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_ned_m_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    body_z: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    yaw_rad: float = 0.0
    thrust_m_s2: float = 0.0
    R_world_body: np.ndarray = field(default_factory=lambda: np.eye(3))
    angular_velocity_body_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    on_ground: bool = True


class MultirotorDynamics:
    """Integrates one multirotor. Command with :meth:`step` (thrust direction + magnitude, yaw rate)."""

    def __init__(self, limits: DynamicsLimits, position_ned_m, yaw_rad: float = 0.0, ground_down_m: float = 0.0):
        self.limits = limits
        self.ground_down_m = float(ground_down_m)
        self.state = RigidBodyState(
            position_ned_m=np.asarray(position_ned_m, dtype=float).copy(), yaw_rad=float(yaw_rad)
        )
        self.state.R_world_body = R_from_body_z_and_yaw(self.state.body_z, self.state.yaw_rad)

    def step(
        self,
        dt_s: float,
        body_z_cmd: np.ndarray,
        thrust_cmd_m_s2: float,
        yaw_rate_cmd_rad_s: float,
        wind_ned_m_s: np.ndarray,
        motors_on: bool = True,
    ) -> RigidBodyState:
        """Advance ``dt_s`` seconds.

        Args:
            body_z_cmd: (3,) desired body z axis in NED (unit; -thrust direction), tilt-limited here.
            thrust_cmd_m_s2: desired specific thrust magnitude (hover = g), clipped to [0, max_thrust].
            yaw_rate_cmd_rad_s: desired yaw rate, clipped to the yaw-rate limit.
            wind_ned_m_s: (3,) air velocity in NED.
            motors_on: False (disarmed) -> no thrust, the attitude relaxes to level.
        """
        s, lim = self.state, self.limits
        if not motors_on:
            body_z_cmd = np.array([0.0, 0.0, 1.0])
            thrust_cmd_m_s2 = 0.0
            yaw_rate_cmd_rad_s = 0.0
        if s.on_ground:  # landing gear on the ground: the vehicle stays level until it lifts off
            body_z_cmd = np.array([0.0, 0.0, 1.0])
        body_z_cmd = limit_tilt(np.asarray(body_z_cmd, dtype=float), lim.max_tilt_rad)
        # attitude: first-order towards the commanded thrust direction (then re-limited, re-normalised)
        a = min(1.0, dt_s / lim.attitude_time_constant_s)
        z = s.body_z + a * (body_z_cmd - s.body_z)
        z = limit_tilt(z / math.sqrt(z[0] * z[0] + z[1] * z[1] + z[2] * z[2]), lim.max_tilt_rad)
        yaw_rate = float(np.clip(yaw_rate_cmd_rad_s, -lim.max_yaw_rate_rad_s, lim.max_yaw_rate_rad_s))
        if s.on_ground and not motors_on:
            yaw_rate = 0.0
        yaw = (s.yaw_rad + yaw_rate * dt_s + math.pi) % (2 * math.pi) - math.pi
        R_prev = s.R_world_body
        R = R_from_body_z_and_yaw(z, yaw)
        # body rates from the attitude change (small-angle log map of R_prev^T R)
        dR = R_prev.T @ R
        omega = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / (2.0 * dt_s)
        # thrust magnitude: first-order lag
        thrust_cmd = float(np.clip(thrust_cmd_m_s2, 0.0, lim.max_thrust_m_s2))
        b = min(1.0, dt_s / lim.thrust_time_constant_s)
        thrust = s.thrust_m_s2 + b * (thrust_cmd - s.thrust_m_s2)
        # translational dynamics (semi-implicit Euler)
        accel = (
            -thrust * z + G_NED + lim.drag_per_mass_1_s * (np.asarray(wind_ned_m_s, dtype=float) - s.velocity_ned_m_s)
        )
        vel = s.velocity_ned_m_s + accel * dt_s
        pos = s.position_ned_m + vel * dt_s
        on_ground = False
        if pos[2] >= self.ground_down_m:
            # contact: the ground holds the vehicle (no bounce, no sliding)
            pos[2] = self.ground_down_m
            if vel[2] >= 0.0 or s.on_ground:
                on_ground = -thrust * z[2] + GRAVITY_M_S2 >= 0.0  # not enough lift to leave
            if on_ground:
                vel = np.zeros(3)
                pos[:2] = s.position_ned_m[:2]
                accel = np.zeros(3)
            else:
                vel[2] = min(vel[2], 0.0)
        s.position_ned_m, s.velocity_ned_m_s, s.accel_ned_m_s2 = pos, vel, accel
        s.body_z, s.yaw_rad, s.R_world_body, s.thrust_m_s2 = z, yaw, R, thrust
        s.angular_velocity_body_rad_s = omega
        s.on_ground = on_ground
        return s
