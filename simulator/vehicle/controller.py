"""PX4's multicopter position controller (``mc_pos_control`` / ``PositionControl.cpp``), in SI units.

One step, as PX4 (PX4-Autopilot ``src/modules/mc_pos_control/PositionControl/PositionControl.cpp``):

* position: ``vel_sp = vel_ff + MPC_XY_P / MPC_Z_P * (pos_sp - pos)`` (NaN components have no influence);
  the horizontal part is limited to ``MPC_XY_VEL_MAX`` giving the position correction priority over the
  feed-forward (``ControlMath::constrainXY``), the vertical part to ``MPC_Z_VEL_MAX_UP`` / ``_DN``;
* velocity: ``acc_sp = acc_ff + P * (vel_sp - vel) + I + -D * vel_dot`` with PX4's acceleration-unit gains
  (``MPC_XY_VEL_P_ACC`` 1.8, ``_I_ACC`` 0.4, ``_D_ACC`` 0.2, ``MPC_Z_VEL_P_ACC`` 4, ``_I_ACC`` 2, ``_D_ACC`` 0),
  ``vel_dot`` the vehicle's acceleration low-passed at ``MPC_VELD_LP`` (5 Hz); the vertical integral is bounded
  to +-g and frozen while the thrust saturates, the horizontal one uses PX4's tracking anti-windup;
* acceleration -> thrust: body z axis from ``(-ax, -ay, g - az)``, tilt limited to ``MPC_TILTMAX_AIR``, collective
  thrust = the vertical demand projected on that axis, at least ``MPC_THR_MIN``; vertical thrust has priority
  over horizontal up to a horizontal margin (``MPC_THR_XY_MARG``).

Thrust is *specific* (m/s^2; hover = g), so PX4's hover-thrust scaling drops out. Offboard setpoints reach
:meth:`PositionController.update` unchanged (PX4 does no smoothing in offboard); the auto modes (takeoff,
hold, return) smooth their own setpoints (:class:`AutoTrajectory`, PX4's flight tasks in spirit).
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
    the autopilot's parameters then update); the thrust bounds are the airframe's (MPC_THR_MIN / MPC_THR_MAX
    with MPC_THR_HOVER = 0.5: 0.24 g .. 2 g)."""

    max_speed_xy_m_s: float
    max_speed_up_m_s: float
    max_speed_down_m_s: float
    max_accel_xy_m_s2: float
    max_accel_z_m_s2: float
    max_tilt_rad: float
    max_yaw_rate_rad_s: float
    min_thrust_m_s2: float = 0.12 * GRAVITY_M_S2
    max_thrust_m_s2: float = 1.9 * GRAVITY_M_S2
    #: horizontal thrust kept free when vertical thrust has priority (MPC_THR_XY_MARG 0.3 of hover*2)
    xy_thrust_margin_m_s2: float = 0.3 * 2.0 * GRAVITY_M_S2

    @classmethod
    def from_config(cls, limits: LimitsConfig | None = None) -> ControllerLimits:
        L = limits or LimitsConfig()
        return cls(max_speed_xy_m_s=L.max_speed_xy_m_s, max_speed_up_m_s=L.max_speed_up_m_s,
                   max_speed_down_m_s=L.max_speed_down_m_s, max_accel_xy_m_s2=L.max_accel_xy_m_s2,
                   max_accel_z_m_s2=L.max_accel_z_m_s2, max_tilt_rad=math.radians(L.max_tilt_deg),
                   max_yaw_rate_rad_s=math.radians(L.max_yaw_rate_deg_s))


def constrain_xy(v0: np.ndarray, v1: np.ndarray, max_norm: float) -> np.ndarray:
    """PX4 ``ControlMath::constrainXY``: ``v0 + v1`` limited to ``max_norm``, keeping ``v0`` (the position
    correction) first and as much of ``v1`` (the feed-forward) along its own direction as fits."""
    s = v0 + v1
    if float(np.hypot(*s)) <= max_norm:
        return s
    n0 = float(np.hypot(*v0))
    if n0 >= max_norm:
        return v0 / n0 * max_norm
    n1 = float(np.hypot(*v1))
    if n1 < 1e-9:
        return v0
    u1 = v1 / n1
    # largest s >= 0 with |v0 + s u1| = max_norm
    b = float(u1 @ v0)
    c = n0 * n0 - max_norm * max_norm
    s_len = -b + math.sqrt(max(b * b - c, 0.0))
    return v0 + s_len * u1


class PositionController:
    """Stateful (velocity integral, filtered acceleration); call :meth:`update` at the physics rate."""

    def __init__(self, limits: ControllerLimits | None = None, gains: ControllerConfig | None = None):
        self.limits = limits or ControllerLimits.from_config()
        self.gains = gains or ControllerConfig()
        self.reset()

    def reset(self, velocity_ned_m_s: np.ndarray | None = None) -> None:
        """Clear the integral and the acceleration filter (``velocity_ned_m_s``: kept for the caller's record)."""
        self._vel_int = [0.0, 0.0, 0.0]
        self._vel_dot = [0.0, 0.0, 0.0]
        self.velocity_setpoint_ned_m_s = np.zeros(3) if velocity_ned_m_s is None else np.asarray(velocity_ned_m_s, float).copy()
        self.accel_setpoint_ned_m_s2 = np.zeros(3)

    def update(
        self,
        dt_s: float,
        sp: TrajectorySetpoint,
        position_ned_m: np.ndarray,
        velocity_ned_m_s: np.ndarray,
        yaw_rad: float,
        landed: bool,
        accel_ned_m_s2: np.ndarray | None = None,
    ) -> tuple[np.ndarray, float, float]:
        """One control step from the (estimated) state; ``accel_ned_m_s2`` (3,) is the vehicle's acceleration
        (PX4's velocity derivative; None: no D term).

        Returns:
            body_z_cmd (3,) unit (FRD body z in NED, i.e. pointing down), thrust_m_s2 (specific thrust
            magnitude), yaw_rate_cmd_rad_s.
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

        vmax_xy = lim.max_speed_xy_m_s if math.isnan(sp.max_speed_xy_m_s) else min(sp.max_speed_xy_m_s, lim.max_speed_xy_m_s)
        vmax_up = lim.max_speed_up_m_s if math.isnan(sp.max_speed_up_m_s) else min(sp.max_speed_up_m_s, lim.max_speed_up_m_s)
        vmax_dn = (lim.max_speed_down_m_s if math.isnan(sp.max_speed_down_m_s)
                   else min(sp.max_speed_down_m_s, lim.max_speed_down_m_s))

        # (per-axis Python floats: this runs at the physics rate for every vehicle; numpy on 3-vectors is slower)
        nan = math.nan
        pos_sp = sp.position_ned_m.tolist()
        vel_ff = sp.velocity_ned_m_s.tolist()
        acc_ff = sp.accel_ned_m_s2.tolist()
        pos = np.asarray(position_ned_m, float).tolist()
        vel = np.asarray(velocity_ned_m_s, float).tolist()

        # --- position P -> velocity setpoint (+ feed-forward), PX4 _positionControl ---
        kp = (g.pos_xy_p, g.pos_xy_p, g.pos_z_p)
        vel_from_pos = [kp[k] * (pos_sp[k] - pos[k]) for k in range(3)]  # NaN where no position setpoint
        vel_sp = [0.0, 0.0, 0.0]
        for k in range(3):  # addIfNotNan: a NaN feed-forward leaves the position term alone (NaN if neither)
            ff, fp = vel_ff[k], vel_from_pos[k]
            vel_sp[k] = fp if math.isnan(ff) else (ff if math.isnan(fp) else ff + fp)
        vfp = [0.0 if math.isnan(x) else x for x in vel_from_pos]
        if not (math.isnan(vel_sp[0]) or math.isnan(vel_sp[1])):
            xy = constrain_xy(np.array(vfp[:2]), np.array([vel_sp[0] - vfp[0], vel_sp[1] - vfp[1]]), vmax_xy)
            vel_sp[0], vel_sp[1] = float(xy[0]), float(xy[1])
        if not math.isnan(vel_sp[2]):
            vel_sp[2] = min(max(vel_sp[2], -vmax_up), vmax_dn)
        self.velocity_setpoint_ned_m_s = np.array(vel_sp)

        # --- velocity PID -> acceleration setpoint, PX4 _velocityControl ---
        vd, vi = self._vel_dot, self._vel_int
        if accel_ned_m_s2 is not None:  # velocity derivative, low-passed at MPC_VELD_LP
            a = 1.0 - math.exp(-2.0 * math.pi * g.vel_deriv_lp_hz * dt_s) if g.vel_deriv_lp_hz > 0 else 1.0
            acc_now = np.asarray(accel_ned_m_s2, float).tolist()
            vd = [vd[k] + a * (acc_now[k] - vd[k]) for k in range(3)]
        vi[2] = min(max(vi[2], -GRAVITY_M_S2), GRAVITY_M_S2)
        kvp = (g.vel_xy_p, g.vel_xy_p, g.vel_z_p)
        kvi = (g.vel_xy_i, g.vel_xy_i, g.vel_z_i)
        kvd = (g.vel_xy_d, g.vel_xy_d, g.vel_z_d)
        vel_err = [vel_sp[k] - vel[k] for k in range(3)]  # NaN where no velocity control
        acc_sp = [0.0, 0.0, 0.0]
        for k in range(3):
            fb = kvp[k] * vel_err[k] + vi[k] - kvd[k] * vd[k]
            ff = acc_ff[k]
            x = fb if math.isnan(ff) else (ff if math.isnan(fb) else ff + fb)
            acc_sp[k] = 0.0 if math.isnan(x) else x
        if landed:
            acc_sp[0] = acc_sp[1] = 0.0
        self._vel_dot = vd
        self.accel_setpoint_ned_m_s2 = np.array(acc_sp)
        body_z, thrust, thr_vec = self._acceleration_control(self.accel_setpoint_ned_m_s2)

        # integrator: vertical anti-windup while the thrust saturates, horizontal tracking anti-windup
        vel_err = [0.0 if math.isnan(x) else x for x in vel_err]
        tz = -float(thr_vec[2])
        if (tz <= lim.min_thrust_m_s2 + 1e-9 and vel_err[2] >= 0.0) or (tz >= lim.max_thrust_m_s2 - 1e-9 and vel_err[2] <= 0.0):
            vel_err[2] = 0.0
        px_, py_ = float(thr_vec[0]), float(thr_vec[1])  # specific force: the horizontal acceleration produced
        lx, ly = (px_, py_) if acc_sp[0] ** 2 + acc_sp[1] ** 2 > px_ * px_ + py_ * py_ else (acc_sp[0], acc_sp[1])
        if g.vel_xy_p > 0:
            arw = 2.0 / g.vel_xy_p
            vel_err[0] -= arw * (acc_sp[0] - lx)
            vel_err[1] -= arw * (acc_sp[1] - ly)
        if landed and (math.isnan(vel_sp[2]) or vel_sp[2] >= 0.0):
            self._vel_int = [0.0, 0.0, 0.0]  # on the ground and not climbing: PX4 resets the integral
        else:
            self._vel_int = [vi[k] + kvi[k] * vel_err[k] * dt_s for k in range(3)]
        return body_z, thrust, yaw_rate

    def _acceleration_control(self, acc_sp: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
        """PX4 _accelerationControl + the thrust saturation of _velocityControl: (body z FRD, thrust, thrust
        vector (specific force, NED, pointing up when hovering))."""
        lim = self.limits
        ax, ay, az = (float(x) for x in acc_sp)
        # body z axis (FRD, pointing down when level) of the demanded specific force; PX4's body_z
        bx, by, bz = -ax, -ay, GRAVITY_M_S2 - az
        n = math.sqrt(bx * bx + by * by + bz * bz)
        if n > 1e-9:
            bx, by, bz = bx / n, by / n, bz / n
        else:
            bx, by, bz = 0.0, 0.0, 1.0
        if bz < math.cos(lim.max_tilt_rad):  # PX4 ControlMath::limitTilt
            h = math.hypot(bx, by)
            if h < 1e-9:
                bx, by, bz = 0.0, 0.0, 1.0
            else:
                st = math.sin(lim.max_tilt_rad)
                bx, by, bz = bx / h * st, by / h * st, math.cos(lim.max_tilt_rad)
        thrust_ned_z = az - GRAVITY_M_S2  # negative = up
        collective = min(thrust_ned_z / max(bz, 1e-3), -lim.min_thrust_m_s2)  # negative
        tx, ty, tz = bx * collective, by * collective, bz * collective  # specific force, NED (z < 0 lifting)
        # vertical priority keeping a horizontal margin, then horizontal saturation (PX4 _velocityControl)
        txy = math.hypot(tx, ty)
        tmax2 = lim.max_thrust_m_s2 ** 2
        tz_max2 = tmax2 - min(txy, lim.xy_thrust_margin_m_s2) ** 2
        tz = max(tz, -math.sqrt(max(tz_max2, 0.0)))
        txy_max2 = tmax2 - tz * tz
        txy_max = math.sqrt(txy_max2) if txy_max2 > 0 else 0.0
        if txy > txy_max:
            tx, ty = tx * txy_max / txy, ty * txy_max / txy
        thrust = math.sqrt(tx * tx + ty * ty + tz * tz)
        thr = np.array([tx, ty, tz])
        body_z = -thr / thrust if thrust > 1e-9 else np.array([0.0, 0.0, 1.0])
        return body_z, thrust, thr

    def thrust_from_accel(self, accel_ned_m_s2: np.ndarray) -> tuple[np.ndarray, float]:
        """Body z axis (3,) and specific thrust for a desired acceleration (tilt limit, vertical priority)."""
        body_z, thrust, _ = self._acceleration_control(np.asarray(accel_ned_m_s2, float))
        return body_z, thrust

    def _yaw_rate(self, sp: TrajectorySetpoint, yaw_rad: float) -> float:
        lim = self.limits
        rate = 0.0 if math.isnan(sp.yaw_rate_rad_s) else sp.yaw_rate_rad_s
        if not math.isnan(sp.yaw_rad):
            err = (sp.yaw_rad - yaw_rad + math.pi) % (2 * math.pi) - math.pi
            rate += self.gains.yaw_p * err
        return min(max(float(rate), -lim.max_yaw_rate_rad_s), lim.max_yaw_rate_rad_s)


def _braking_speed(dist_m: float, p_gain: float, accel_m_s2: float) -> float:
    """Speed towards a target ``dist_m`` (>= 0) away: P near it, sqrt(2 a d) further out (stops in time)."""
    return min(p_gain * dist_m, math.sqrt(2.0 * accel_m_s2 * dist_m))


class AutoTrajectory:
    """Smoothed position/velocity/acceleration setpoints towards a target point for the auto modes (takeoff,
    hold, return; PX4's flight tasks with their jerk-limited trajectory in spirit: here acceleration-limited with
    a square-root braking curve). :meth:`reset` at mode entry from the vehicle's estimated state; :meth:`step`
    once per control step gives the :class:`TrajectorySetpoint` for :class:`PositionController`."""

    def __init__(self, position_ned_m: np.ndarray | None = None, velocity_ned_m_s: np.ndarray | None = None):
        self.reset(np.zeros(3) if position_ned_m is None else position_ned_m, velocity_ned_m_s)

    def reset(self, position_ned_m: np.ndarray, velocity_ned_m_s: np.ndarray | None = None) -> None:
        self.position_ned_m = np.asarray(position_ned_m, float).copy()
        self.velocity_ned_m_s = np.zeros(3) if velocity_ned_m_s is None else np.asarray(velocity_ned_m_s, float).copy()

    def step(self, dt_s: float, target_ned_m: np.ndarray, max_speed_xy_m_s: float, max_speed_up_m_s: float,
             max_speed_down_m_s: float, accel_xy_m_s2: float, accel_z_m_s2: float,
             p_gain_xy: float = 1.0, p_gain_z: float = 1.0) -> TrajectorySetpoint:
        """Advance the trajectory by ``dt_s`` towards ``target_ned_m`` (3,) within the speed and acceleration
        limits; returns position + velocity + acceleration setpoints (yaw unset)."""
        e = np.asarray(target_ned_m, float) - self.position_ned_m
        v_des = np.zeros(3)
        d = float(np.hypot(e[0], e[1]))
        if d > 1e-9:
            v_des[:2] = e[:2] / d * min(_braking_speed(d, p_gain_xy, 0.8 * accel_xy_m_s2), max_speed_xy_m_s)
        v_des[2] = math.copysign(_braking_speed(abs(e[2]), p_gain_z, 0.8 * accel_z_m_s2), e[2])
        v_des[2] = min(max(v_des[2], -max_speed_up_m_s), max_speed_down_m_s)
        dv = v_des - self.velocity_ned_m_s
        dxy = float(np.hypot(dv[0], dv[1]))
        if dxy > accel_xy_m_s2 * dt_s:
            dv[:2] *= accel_xy_m_s2 * dt_s / dxy
        dv[2] = min(max(dv[2], -accel_z_m_s2 * dt_s), accel_z_m_s2 * dt_s)
        self.velocity_ned_m_s = self.velocity_ned_m_s + dv
        self.position_ned_m = self.position_ned_m + self.velocity_ned_m_s * dt_s
        return TrajectorySetpoint(position_ned_m=self.position_ned_m.copy(),
                                  velocity_ned_m_s=self.velocity_ned_m_s.copy(), accel_ned_m_s2=dv / dt_s)
