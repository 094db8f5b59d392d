"""A 2-axis camera gimbal (pitch, yaw; roll stabilised at 0): the pure dynamics of one vehicle's gimbal.

No I/O: :class:`simulator.vehicle.mavlink_endpoint.MavlinkEndpoint` speaks the MAVLink gimbal protocol v2 for it
(the autopilot as gimbal manager of this non-MAVLink gimbal device, as PX4 does) and turns commands into
:meth:`SimGimbal.set_angles` / :meth:`SimGimbal.set_rates`; :class:`simulator.vehicle.autopilot.SimVehicle` steps it.

Angles (radians), as the MAVLink gimbal protocol reports them: ``pitch_rad`` relative to the horizon (roll and
pitch are stabilised; negative = down), ``yaw_rad`` relative to the vehicle's heading (positive = right). Each
axis follows its target through a first-order lag (``time_constant_s``) whose rate is limited
(``max_rate_deg_s``); targets and angles are clamped to the mechanical limits. Yaw modes:

* follow (``yaw_lock=False``): the target yaw is relative to the vehicle heading, the camera turns with it;
* lock (``yaw_lock=True``): the target yaw is relative to north; the gimbal counter-turns as the vehicle yaws
  (within its yaw limits and rate).

The yaw axis has end stops (no slip ring): between them it moves the way that stays inside the limits, even
when the other way round is shorter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from simulator.config import GimbalConfig

__all__ = ["GimbalConfig", "SimGimbal", "GimbalState", "quat_wxyz_from_pitch_yaw"]  # GimbalConfig: simulator.config


@dataclass(frozen=True)
class GimbalState:
    """The gimbal's true attitude at one instant (radians, rad/s; see the module doc for the frames)."""

    pitch_rad: float
    yaw_rad: float
    pitch_rate_rad_s: float
    yaw_rate_rad_s: float
    yaw_lock: bool


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _clamp(x: float, lo: float, hi: float) -> float:
    return min(max(x, lo), hi)


class SimGimbal:
    """The dynamics of one 2-axis gimbal (see the module doc). Step it with the vehicle's true yaw."""

    def __init__(self, cfg: GimbalConfig):
        self.cfg = cfg.validate()
        r = math.radians
        self.pitch_limits_rad = (r(cfg.pitch_min_deg), r(cfg.pitch_max_deg))
        self.yaw_limits_rad = (r(cfg.yaw_min_deg), r(cfg.yaw_max_deg))
        self.max_rate_rad_s = r(cfg.max_rate_deg_s)
        self.pitch_rad = _clamp(r(cfg.initial_pitch_deg), *self.pitch_limits_rad)
        self.yaw_rad = 0.0
        self.pitch_rate_rad_s = 0.0
        self.yaw_rate_rad_s = 0.0
        #: targets: pitch relative to the horizon; yaw relative to the heading (follow) or north (lock)
        self.target_pitch_rad = self.pitch_rad
        self.target_yaw_rad = 0.0
        self.yaw_lock = False
        #: rate commands (rad/s) moving the target; None: angle control
        self._target_rates: tuple[float, float] | None = None
        self.commands = 0
        #: the gimbal manager's (the autopilot's) control assignment: (sysid, compid) of the primary and the
        #: secondary controller, (0, 0) = none (MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE)
        self.primary_control: tuple[int, int] = (0, 0)
        self.secondary_control: tuple[int, int] = (0, 0)

    def set_angles(self, pitch_rad: float, yaw_rad: float, yaw_lock: bool = False, vehicle_yaw_rad: float = 0.0) -> None:
        """Point at ``pitch_rad`` (relative to the horizon) and ``yaw_rad`` (relative to the heading, or to north
        when ``yaw_lock``). A NaN angle keeps that axis' current target. Targets beyond the limits are clamped."""
        self.commands += 1
        self._target_rates = None
        if yaw_lock != self.yaw_lock:  # re-express the held yaw target in the new frame
            self.target_yaw_rad = (self.target_yaw_rad + vehicle_yaw_rad) if yaw_lock else \
                (self.target_yaw_rad - vehicle_yaw_rad)
            self.target_yaw_rad = _wrap(self.target_yaw_rad)
            self.yaw_lock = yaw_lock
        if math.isfinite(pitch_rad):
            self.target_pitch_rad = _clamp(pitch_rad, *self.pitch_limits_rad)
        if math.isfinite(yaw_rad):
            self.target_yaw_rad = _wrap(yaw_rad) if yaw_lock else _clamp(yaw_rad, *self.yaw_limits_rad)

    def set_rates(self, pitch_rate_rad_s: float, yaw_rate_rad_s: float, yaw_lock: bool = False,
                  vehicle_yaw_rad: float = 0.0) -> None:
        """Move the targets at these rates (clamped to the rate limit; NaN = 0) until the next command."""
        self.set_angles(math.nan, math.nan, yaw_lock, vehicle_yaw_rad)
        lim = self.max_rate_rad_s
        self._target_rates = tuple(_clamp(x if math.isfinite(x) else 0.0, -lim, lim)
                                   for x in (pitch_rate_rad_s, yaw_rate_rad_s))

    def yaw_target_relative_rad(self, vehicle_yaw_rad: float) -> float:
        """The yaw target relative to the heading now (within the limits)."""
        y = _wrap(self.target_yaw_rad - vehicle_yaw_rad) if self.yaw_lock else self.target_yaw_rad
        return _clamp(y, *self.yaw_limits_rad)

    def step(self, dt_s: float, vehicle_yaw_rad: float = 0.0) -> None:
        """Advance ``dt_s`` seconds with the vehicle's true heading ``vehicle_yaw_rad``."""
        if dt_s <= 0:
            return
        if self._target_rates is not None:
            pr, yr = self._target_rates
            self.target_pitch_rad = _clamp(self.target_pitch_rad + pr * dt_s, *self.pitch_limits_rad)
            ty = self.target_yaw_rad + yr * dt_s
            self.target_yaw_rad = _wrap(ty) if self.yaw_lock else _clamp(ty, *self.yaw_limits_rad)
        tau = self.cfg.time_constant_s
        lim = self.max_rate_rad_s
        # yaw: the target relative to the heading; a lock target may wrap, the axis itself has end stops
        targets = (self.target_pitch_rad, self.yaw_target_relative_rad(vehicle_yaw_rad))
        new = []
        for angle, target, limits in ((self.pitch_rad, targets[0], self.pitch_limits_rad),
                                      (self.yaw_rad, targets[1], self.yaw_limits_rad)):
            err = target - angle
            # exact first-order step (stable for any dt), then the rate limit
            step = err * (1.0 - math.exp(-dt_s / tau)) if tau > 0 else err
            step = _clamp(step, -lim * dt_s, lim * dt_s)
            new.append(_clamp(angle + step, *limits))
        self.pitch_rate_rad_s = (new[0] - self.pitch_rad) / dt_s
        self.yaw_rate_rad_s = (new[1] - self.yaw_rad) / dt_s
        self.pitch_rad, self.yaw_rad = new

    def state(self) -> GimbalState:
        return GimbalState(self.pitch_rad, self.yaw_rad, self.pitch_rate_rad_s, self.yaw_rate_rad_s, self.yaw_lock)


def quat_wxyz_from_pitch_yaw(pitch_rad: float, yaw_rad: float) -> tuple[float, float, float, float]:
    """The attitude quaternion (w, x, y, z) of roll 0, ``pitch_rad``, ``yaw_rad`` (ZYX Euler, as MAVLink)."""
    cp, sp = math.cos(pitch_rad / 2), math.sin(pitch_rad / 2)
    cy, sy = math.cos(yaw_rad / 2), math.sin(yaw_rad / 2)
    return (cy * cp, -sy * sp, cy * sp, sy * cp)
