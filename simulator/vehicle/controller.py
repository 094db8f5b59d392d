"""PX4-like multicopter position/velocity controller (``mc_pos_control`` in spirit, simplified).

Cascade: position error -> velocity setpoint (P, with a square-root braking curve so that the
acceleration limit is respected when stopping) -> slew-limited to the acceleration limits -> velocity
PI -> acceleration setpoint -> thrust vector (tilt limited, vertical thrust prioritised, as PX4) ->
``(body_z_cmd, thrust_m_s2)`` for :class:`~simulator.vehicle.dynamics.MultirotorDynamics`.
Yaw: P on the yaw error (or a yaw-rate feed-forward), rate-limited.

Setpoints follow the MAVLink ``SET_POSITION_TARGET_LOCAL_NED`` convention: a NaN component is not
controlled (e.g. position NaN + velocity set = velocity control on that axis).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from simulator.config import ControllerConfig, LimitsConfig
from simulator.vehicle.dynamics import GRAVITY_M_S2

NAN3 = np.full(3, np.nan)


@dataclass
class TrajectorySetpoint:
    """What the flight mode wants (PX4's ``trajectory_setpoint``). Shapes (3,) NED in the vehicle's local frame;
    NaN = not set.

    Not the agent's :class:`onboard.setpoint.Setpoint` (world frame, fully set, camera pitch), which reaches the
    vehicle only as MAVLink ``SET_POSITION_TARGET_LOCAL_NED`` and is turned into one of these by the endpoint.
    """

    position_ned_m: np.ndarray = field(default_factory=lambda: NAN3.copy())
    velocity_ned_m_s: np.ndarray = field(default_factory=lambda: NAN3.copy())
    accel_ned_m_s2: np.ndarray = field(default_factory=lambda: NAN3.copy())
    yaw_rad: float = math.nan
    yaw_rate_rad_s: float = math.nan
    #: optional tighter limits for this setpoint (takeoff/land speed, cruise speed); NaN = vehicle limits
    max_speed_xy_m_s: float = math.nan
    max_speed_up_m_s: float = math.nan
    max_speed_down_m_s: float = math.nan
    #: attitude control (SET_ATTITUDE_TARGET): body z axis (3,) and specific thrust; overrides the rest
    body_z_cmd: np.ndarray | None = None
    thrust_m_s2: float = math.nan


@dataclass
class ControllerLimits:
    """The controller's envelope in SI units, built from the simulator's ``[limits]`` (PX4's MPC_* values, which
    the autopilot's parameters then update); the thrust bounds are the airframe's."""

    max_speed_xy_m_s: float
    max_speed_up_m_s: float
    max_speed_down_m_s: float
    max_accel_xy_m_s2: float
    max_accel_z_m_s2: float
    max_tilt_rad: float
    max_yaw_rate_rad_s: float
    min_thrust_m_s2: float = 0.12 * GRAVITY_M_S2
    max_thrust_m_s2: float = 1.9 * GRAVITY_M_S2

    @classmethod
    def from_config(cls, limits: LimitsConfig | None = None) -> ControllerLimits:
        L = limits or LimitsConfig()
        return cls(max_speed_xy_m_s=L.max_speed_xy_m_s, max_speed_up_m_s=L.max_speed_up_m_s,
                   max_speed_down_m_s=L.max_speed_down_m_s, max_accel_xy_m_s2=L.max_accel_xy_m_s2,
                   max_accel_z_m_s2=L.max_accel_z_m_s2, max_tilt_rad=math.radians(L.max_tilt_deg),
                   max_yaw_rate_rad_s=math.radians(L.max_yaw_rate_deg_s))


def _sqrt_braking_speed(err_m: float, p_gain: float, accel_m_s2: float) -> float:
    """Speed towards a target ``err_m`` away: P near the target, sqrt(2 a d) far away (stops in time)."""
    d = abs(err_m)
    return math.copysign(min(p_gain * d, math.sqrt(2.0 * accel_m_s2 * d)), err_m)


class PositionController:
    """Stateful (integrators, smoothed velocity setpoint); call :meth:`update` at the physics rate."""

    def __init__(self, limits: ControllerLimits | None = None, gains: ControllerConfig | None = None):
        self.limits = limits or ControllerLimits.from_config()
        self.gains = gains or ControllerConfig()
        self.reset()

    def reset(self, velocity_ned_m_s: np.ndarray | None = None) -> None:
        """Clear the integrators and start the velocity setpoint at ``velocity_ned_m_s`` (default 0)."""
        self._vel_int = np.zeros(3)
        self._vel_sp = np.zeros(3) if velocity_ned_m_s is None else np.asarray(velocity_ned_m_s, float).copy()
        self.velocity_setpoint_ned_m_s = self._vel_sp.copy()

    def update(
        self,
        dt_s: float,
        sp: TrajectorySetpoint,
        position_ned_m: np.ndarray,
        velocity_ned_m_s: np.ndarray,
        yaw_rad: float,
        landed: bool,
    ) -> tuple[np.ndarray, float, float]:
        """One control step from the (estimated) state.

        Returns:
            body_z_cmd (3,) unit, thrust_m_s2 (specific thrust magnitude), yaw_rate_cmd_rad_s.
        """
        lim, g = self.limits, self.gains
        yaw_rate = self._yaw_rate(sp, yaw_rad)
        if sp.body_z_cmd is not None:  # attitude setpoint: pass through
            z = np.asarray(sp.body_z_cmd, float)
            self.reset(velocity_ned_m_s)
            return z / np.linalg.norm(z), float(np.clip(sp.thrust_m_s2, 0.0, lim.max_thrust_m_s2)), yaw_rate
        if (
            np.isnan(sp.position_ned_m).all()
            and np.isnan(sp.velocity_ned_m_s).all()
            and not np.isnan(sp.accel_ned_m_s2).all()
        ):  # acceleration-only setpoint (MAVSDK set_acceleration_ned): open loop through the thrust vector
            self.reset(velocity_ned_m_s)
            acc = np.nan_to_num(sp.accel_ned_m_s2)
            if landed:
                acc[:2] = 0.0
            return (*self.thrust_from_accel(acc), yaw_rate)

        vmax_xy = (
            lim.max_speed_xy_m_s if math.isnan(sp.max_speed_xy_m_s) else min(sp.max_speed_xy_m_s, lim.max_speed_xy_m_s)
        )
        vmax_up = (
            lim.max_speed_up_m_s if math.isnan(sp.max_speed_up_m_s) else min(sp.max_speed_up_m_s, lim.max_speed_up_m_s)
        )
        vmax_dn = (
            lim.max_speed_down_m_s
            if math.isnan(sp.max_speed_down_m_s)
            else min(sp.max_speed_down_m_s, lim.max_speed_down_m_s)
        )

        # --- velocity setpoint from position error (+ velocity feed-forward) ---
        v_des = np.zeros(3)
        pos_sp, vel_ff = sp.position_ned_m, sp.velocity_ned_m_s
        if not (math.isnan(pos_sp[0]) or math.isnan(pos_sp[1])):
            e = pos_sp[:2] - position_ned_m[:2]
            d = math.hypot(e[0], e[1])
            if d > 1e-9:
                v_des[:2] = e / d * _sqrt_braking_speed(d, g.pos_xy_p, 0.8 * lim.max_accel_xy_m_s2)
        if not math.isnan(vel_ff[0]):
            v_des[0] += vel_ff[0]
        if not math.isnan(vel_ff[1]):
            v_des[1] += vel_ff[1]
        if not math.isnan(pos_sp[2]):
            v_des[2] = _sqrt_braking_speed(pos_sp[2] - position_ned_m[2], g.pos_z_p, 0.8 * lim.max_accel_z_m_s2)
        if not math.isnan(vel_ff[2]):
            v_des[2] += vel_ff[2]
        # --- limits: horizontal norm, vertical up/down ---
        sxy = math.hypot(v_des[0], v_des[1])
        if sxy > vmax_xy:
            v_des[:2] *= vmax_xy / sxy
        v_des[2] = min(max(v_des[2], -vmax_up), vmax_dn)
        # --- acceleration limit on the velocity setpoint (trajectory smoothing) ---
        dv = v_des - self._vel_sp
        dxy = math.hypot(dv[0], dv[1])
        step_xy = lim.max_accel_xy_m_s2 * dt_s
        if dxy > step_xy:
            dv[:2] *= step_xy / dxy
        dv[2] = min(max(dv[2], -lim.max_accel_z_m_s2 * dt_s), lim.max_accel_z_m_s2 * dt_s)
        self._vel_sp = self._vel_sp + dv
        self.velocity_setpoint_ned_m_s = self._vel_sp.copy()
        acc_traj = dv / dt_s  # feed-forward of the smoothed trajectory's acceleration (as PX4)

        # --- velocity PI -> acceleration setpoint ---
        ev = self._vel_sp - velocity_ned_m_s
        if landed and self._vel_sp[2] >= 0.0:
            self._vel_int[:] = 0.0
        else:
            self._vel_int[:2] += g.vel_xy_i * ev[:2] * dt_s
            self._vel_int[2] += g.vel_z_i * ev[2] * dt_s
            np.clip(self._vel_int, -4.0, 4.0, out=self._vel_int)
        acc = np.array([g.vel_xy_p * ev[0], g.vel_xy_p * ev[1], g.vel_z_p * ev[2]]) + self._vel_int + acc_traj
        acc_ff = sp.accel_ned_m_s2
        if not math.isnan(acc_ff[0]):
            acc = acc + np.nan_to_num(acc_ff)
        if landed:
            acc[:2] = 0.0
        return (*self.thrust_from_accel(acc), yaw_rate)

    def thrust_from_accel(self, accel_ned_m_s2: np.ndarray) -> tuple[np.ndarray, float]:
        """Body z axis (3,) and specific thrust for a desired acceleration; vertical has priority."""
        lim = self.limits
        f_z = min(accel_ned_m_s2[2] - GRAVITY_M_S2, -lim.min_thrust_m_s2)  # thrust must point up
        f_z = max(f_z, -lim.max_thrust_m_s2)
        max_xy = -f_z * math.tan(lim.max_tilt_rad)
        fx, fy = accel_ned_m_s2[0], accel_ned_m_s2[1]
        nxy = math.hypot(fx, fy)
        if nxy > max_xy:
            fx, fy = fx * max_xy / nxy, fy * max_xy / nxy
        f = np.array([fx, fy, f_z])
        thrust = float(np.linalg.norm(f))
        if thrust > lim.max_thrust_m_s2:  # keep vertical, shrink horizontal
            rem = math.sqrt(max(lim.max_thrust_m_s2**2 - f_z**2, 0.0))
            nxy = math.hypot(fx, fy)
            if nxy > rem and nxy > 0:
                f[:2] *= rem / nxy
            thrust = float(np.linalg.norm(f))
        return -f / thrust, thrust

    def _yaw_rate(self, sp: TrajectorySetpoint, yaw_rad: float) -> float:
        lim = self.limits
        rate = 0.0 if math.isnan(sp.yaw_rate_rad_s) else sp.yaw_rate_rad_s
        if not math.isnan(sp.yaw_rad):
            err = (sp.yaw_rad - yaw_rad + math.pi) % (2 * math.pi) - math.pi
            rate += self.gains.yaw_p * err
        return float(np.clip(rate, -lim.max_yaw_rate_rad_s, lim.max_yaw_rate_rad_s))
