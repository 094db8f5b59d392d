"""Orbit geometry and the orbit setpoint source: pure logic over numpy, no I/O.

Every drone of the fleet flies its phase slot of one shared circle (:class:`shared_msgs.OrbitPlan`).
Drone ``k``'s angle at time ``t`` (radians, in the NED horizontal plane from north towards east)::

    theta_k(t) = phase_offset_rad[k] + direction * angular_speed_rad_s * max(0, t - start_time)

so before the shared start time every drone waits at its starting slot, and after it the slots turn
together (their spacing is fixed by the plan, whatever the clock of each drone's start). Position
``center + radius * (cos theta, sin theta)`` at ``down = -altitude_m``; velocity feed-forward is the
derivative; the camera yaw points at the centre and the gimbal pitch down at it.

:class:`OrbitController` is a :class:`onboard.setpoint.SetpointSource` (the agent's loop asks it for one
:class:`~onboard.setpoint.Setpoint` per tick). It approaches the slot from wherever the vehicle is with a rate-limited
"carrot" (speed ``approach_speed_m_s``), so entering the orbit from a hover never asks the autopilot
for a jump, then tracks the moving slot with velocity feed-forward. The formation MPC
(:class:`onboard.formation.source.FormationSource`) is another.
"""

from __future__ import annotations

import math

import numpy as np

from onboard.setpoint import Setpoint
from shared_msgs import OrbitPlan

__all__ = [
    "OrbitController",
    "slot_angle_rad",
    "slot_state",
    "yaw_to_point_rad",
    "gimbal_pitch_to_point_rad",
    "min_slot_separation_m",
    "evenly_spaced_phases",
]


def slot_angle_rad(plan: OrbitPlan, drone_id: str, t_s: float) -> float:
    """Angle of ``drone_id``'s slot at time ``t_s`` (UNIX seconds); before the start time it stays put."""
    t0 = plan.start_time_ns * 1e-9
    dt = max(0.0, t_s - t0)
    return plan.phase_offset_rad[drone_id] + plan.direction * plan.angular_speed_rad_s * dt


def slot_state(plan: OrbitPlan, drone_id: str, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(position (3,), velocity (3,), acceleration (3,)) of the slot, NED; zero motion before the start."""
    th = slot_angle_rad(plan, drone_id, t_s)
    c = np.asarray(plan.center_ned_m, dtype=float)
    r = plan.radius_m
    pos = np.array([c[0] + r * math.cos(th), c[1] + r * math.sin(th), -plan.altitude_m])
    if t_s < plan.start_time_ns * 1e-9:
        return pos, np.zeros(3), np.zeros(3)
    w = plan.direction * plan.angular_speed_rad_s
    vel = np.array([-r * w * math.sin(th), r * w * math.cos(th), 0.0])
    acc = np.array([-r * w * w * math.cos(th), -r * w * w * math.sin(th), 0.0])
    return pos, vel, acc


def yaw_to_point_rad(from_ned_m, to_ned_m) -> float:
    """Heading (0 = north, + = east) from a position towards a point (horizontal plane)."""
    d = np.asarray(to_ned_m, dtype=float) - np.asarray(from_ned_m, dtype=float)
    return math.atan2(d[1], d[0])


def gimbal_pitch_to_point_rad(from_ned_m, to_ned_m) -> float:
    """Camera pitch (negative = down) from a position towards a point."""
    d = np.asarray(to_ned_m, dtype=float) - np.asarray(from_ned_m, dtype=float)
    return -math.atan2(d[2], math.hypot(d[0], d[1]))


def min_slot_separation_m(plan: OrbitPlan) -> float:
    """Smallest distance between two slots of the plan (chord of the smallest phase gap); inf for < 2."""
    phases = sorted(v % (2 * math.pi) for v in plan.phase_offset_rad.values())
    if len(phases) < 2:
        return math.inf
    gaps = [b - a for a, b in zip(phases, phases[1:])] + [phases[0] + 2 * math.pi - phases[-1]]
    return 2.0 * plan.radius_m * math.sin(min(gaps) / 2.0)


def evenly_spaced_phases(drone_ids: list[str], first_rad: float = 0.0) -> dict[str, float]:
    """Phase offsets 2 pi k / N (k in the given order) starting at ``first_rad``."""
    n = len(drone_ids)
    return {d: float((first_rad + 2.0 * math.pi * k / n) % (2 * math.pi)) for k, d in enumerate(drone_ids)}


class OrbitController:
    """Setpoints for one drone's slot of an :class:`OrbitPlan` (a :class:`~onboard.setpoint.SetpointSource`).

    A carrot point starts at the vehicle's position and moves towards the slot at most at
    ``approach_speed_m_s`` (horizontal) / ``approach_climb_m_s`` (vertical); once it has reached the
    slot it is the slot, streamed with velocity and acceleration feed-forward. Yaw always points the
    camera at the centre (from the carrot, so the heading is smooth), gimbal pitch too unless the plan
    fixes it.

    **Trim** (``trim_gain_per_s`` > 0): once captured, the vehicle's tracking error against its slot (from the
    estimate it reports) is integrated in the orbit's rotating frame (radial, tangential, vertical) and added to the
    streamed position, at most ``trim_max_m``. An autopilot's own integrator works in the world frame; on a circle
    the force it must cancel turns with the vehicle (aerodynamic drag along the track: on PX4 SITL's SIH airframe
    1.2 m/s^2 at 1.2 m/s), so it leaves a steady lag and an outward bias (measured 0.3 s / 2.5 deg and +0.3..0.5 m
    on PX4 SITL without trim). In the rotating frame that error is constant and the trim removes it; a steady
    wind, constant in the world frame, stays with the autopilot's integrator.
    """

    def __init__(self, plan: OrbitPlan, drone_id: str, approach_speed_m_s: float = 3.0, approach_climb_m_s: float = 1.5,
                 trim_gain_per_s: float = 0.0, trim_max_m: float = 1.5):
        if drone_id not in plan.phase_offset_rad:
            raise ValueError(f"plan {plan.plan_id!r} has no phase slot for {drone_id!r}")
        self.plan = plan
        self.drone_id = drone_id
        self.approach_speed_m_s = float(approach_speed_m_s)
        self.approach_climb_m_s = float(approach_climb_m_s)
        self._carrot: np.ndarray | None = None
        self._t_last: float | None = None
        self.captured = False
        self.trim_gain_per_s = float(trim_gain_per_s)
        self.trim_max_m = float(trim_max_m)
        #: the trim in the rotating frame (radial out, tangential along the direction of travel, up), metres
        self.trim_rtu_m = np.zeros(3)

    @property
    def center_ned_m(self) -> np.ndarray:
        return np.asarray(self.plan.center_ned_m, dtype=float)

    def update(self, t_s: float, position_ned_m, velocity_ned_m_s, yaw_rad: float) -> Setpoint:
        slot_p, slot_v, slot_a = slot_state(self.plan, self.drone_id, t_s)
        if self._carrot is None:
            self._carrot = np.asarray(position_ned_m, dtype=float).copy()
            self._t_last = t_s
        dt = min(max(t_s - self._t_last, 0.0), 0.5)
        self._t_last = t_s
        if not self.captured:
            # Move the carrot with the slot's own motion plus a bounded closing speed.
            err = slot_p - self._carrot
            step = err.copy()
            h = math.hypot(err[0], err[1])
            max_h = (self.approach_speed_m_s + float(np.linalg.norm(slot_v[:2]))) * dt
            if h > max_h > 0:
                step[:2] *= max_h / h
            max_v = self.approach_climb_m_s * dt
            step[2] = float(np.clip(err[2], -max_v, max_v))
            self._carrot = self._carrot + step
            vel = step / dt if dt > 0 else np.zeros(3)
            acc = np.zeros(3)
            if float(np.linalg.norm(slot_p - self._carrot)) < 1e-6:
                self.captured = True  # from the next tick on: the slot itself, with feed-forward
            pos = self._carrot
        else:
            self._carrot = slot_p
            pos, vel, acc = slot_p, slot_v, slot_a
            if self.trim_gain_per_s > 0:
                pos = pos + self._trim(slot_p, np.asarray(position_ned_m, dtype=float), dt)
        yaw = yaw_to_point_rad(pos, self.center_ned_m)
        if self.plan.gimbal_pitch_rad is not None:
            pitch = float(self.plan.gimbal_pitch_rad)
        else:
            pitch = gimbal_pitch_to_point_rad(pos, self.center_ned_m)
        return Setpoint(np.array(pos, dtype=float), np.array(vel, dtype=float), yaw, pitch, np.array(acc, dtype=float))

    def _rtu_axes(self, slot_p: np.ndarray) -> np.ndarray:
        """(3, 3) rows: radial-out, tangential (direction of travel) and up unit vectors in NED at the slot."""
        d = slot_p[:2] - self.center_ned_m[:2]
        n = float(np.hypot(d[0], d[1]))
        r = np.array([d[0] / n, d[1] / n, 0.0]) if n > 1e-9 else np.array([1.0, 0.0, 0.0])
        sgn = 1.0 if self.plan.direction >= 0 else -1.0
        t = sgn * np.array([-r[1], r[0], 0.0])
        return np.array([r, t, [0.0, 0.0, -1.0]])

    def _trim(self, slot_p: np.ndarray, position_ned_m: np.ndarray, dt: float) -> np.ndarray:
        """Integrate the slot - vehicle error in the rotating frame; returns the NED offset to add to the slot."""
        axes = self._rtu_axes(slot_p)
        err = slot_p - position_ned_m
        if np.all(np.isfinite(err)) and float(np.linalg.norm(err)) < 2.0 * self.trim_max_m + 1.0:
            self.trim_rtu_m = self.trim_rtu_m + self.trim_gain_per_s * dt * (axes @ err)
            n = float(np.linalg.norm(self.trim_rtu_m))
            if n > self.trim_max_m:
                self.trim_rtu_m *= self.trim_max_m / n
        return axes.T @ self.trim_rtu_m
