"""The formation MPC as the agent's setpoint source (:class:`onboard.orbit.SetpointSource` protocol).

Pure logic: the agent feeds it the fused person estimate (:meth:`FormationSource.set_target`), its slot
angle and the teammates' shared plans as they arrive; the control loop calls :meth:`update` every tick and
shares :attr:`FormationSource.last_plan` with the teammates. Without a person estimate, or when the
failsafe says hold, it holds the position where it was told to hold (brake first: the MPC's fallback).
"""

from __future__ import annotations

import math

import numpy as np

from onboard.formation.mpc import FormationMPC, MpcResult, SharedPlan
from onboard.orbit import Setpoint

__all__ = ["FormationSource"]


class FormationSource:
    """Setpoints from a :class:`FormationMPC` (one MPC step per :meth:`update`).

    Times: ``t_s`` in :meth:`update` is UNIX seconds (the agent's clock), plans carry ns of the same clock.
    Teammate plans older than ``plan_timeout_s`` are dropped (that teammate is then not avoided: the
    failsafe re-spaces the formation once it is declared lost).
    """

    def __init__(self, mpc: FormationMPC, slot_angle_rad: float = 0.0, ground_down_m: float = 0.0, plan_timeout_s: float = 1.0):
        self.mpc = mpc
        self.slot_angle_rad = float(slot_angle_rad)
        self.ground_down_m = float(ground_down_m)
        self.plan_timeout_s = float(plan_timeout_s)
        self._target: tuple[np.ndarray, np.ndarray] | None = None
        self._plans: dict[str, SharedPlan] = {}
        self._states: dict[str, SharedPlan] = {}
        self.hold_position_ned_m: np.ndarray | None = None
        self.last_result: MpcResult | None = None

    @property
    def last_plan(self) -> SharedPlan | None:
        """The plan to share with the teammates (None before the first MPC step)."""
        return None if self.last_result is None else self.last_result.plan

    def set_target(self, position_ned_m, velocity_ned_m_s) -> None:
        """The predicted person (from :class:`onboard.tracking.TrackEstimate`); None position = no target."""
        if position_ned_m is None:
            self._target = None
            return
        self._target = (np.asarray(position_ned_m, dtype=float).copy(), np.asarray(velocity_ned_m_s, dtype=float).copy())

    def set_teammate_plan(self, plan: SharedPlan) -> None:
        if plan.drone_id != self.mpc.drone_id:
            self._plans[plan.drone_id] = plan

    def set_teammate_state(self, drone_id: str, t_ns: int, position_ned_m, velocity_ned_m_s) -> None:
        """A teammate's reported state; used (as a constant-velocity plan) while no fresh plan of it is known,
        e.g. at start-up, so that it is avoided from the first step."""
        if drone_id != self.mpc.drone_id:
            c = self.mpc.cfg
            self._states[drone_id] = SharedPlan.from_state(drone_id, t_ns, position_ned_m, velocity_ned_m_s, c.dt_s, c.horizon_steps)

    def hold(self, position_ned_m=None) -> None:
        """Hold (failsafe): at position_ned_m, or None to resume formation flight."""
        self.hold_position_ned_m = None if position_ned_m is None else np.asarray(position_ned_m, dtype=float).copy()

    def update(self, t_s: float, position_ned_m: np.ndarray, velocity_ned_m_s: np.ndarray, yaw_rad: float) -> Setpoint:
        t_ns = int(round(t_s * 1e9))
        p = np.asarray(position_ned_m, dtype=float)
        if self.hold_position_ned_m is not None or self._target is None:
            hold_at = p if self.hold_position_ned_m is None else self.hold_position_ned_m
            yaw = yaw_rad
            if self._target is not None:
                d = self._target[0] - hold_at
                yaw = math.atan2(d[1], d[0])
            return Setpoint(hold_at.copy(), np.zeros(3), float(yaw))
        fresh = {i: pl for i, pl in self._plans.items() if (t_ns - pl.t0_ns) * 1e-9 <= self.plan_timeout_s}
        self._plans = fresh
        self._states = {i: st for i, st in self._states.items() if (t_ns - st.t0_ns) * 1e-9 <= self.plan_timeout_s}
        fresh = {**self._states, **fresh}  # a plan, where known, replaces the state
        r = self.mpc.step(t_ns, p, velocity_ned_m_s, self._target[0], self._target[1], self.slot_angle_rad, fresh, self.ground_down_m)
        self.last_result = r
        accel = (r.plan_velocities_ned_m_s[1] - r.plan_velocities_ned_m_s[0]) / self.mpc.cfg.dt_s
        return Setpoint(
            position_ned_m=r.setpoint_position_ned_m.copy(),
            velocity_ned_m_s=r.setpoint_velocity_ned_m_s.copy(),
            yaw_rad=r.setpoint_yaw_rad,
            gimbal_pitch_rad=float(r.plan_gimbal_pitch_rad[1]),
            acceleration_ned_m_s2=accel,
        )
