"""The formation MPC as the agent's setpoint source (:class:`onboard.setpoint.SetpointSource` protocol).

Pure logic: the agent feeds it the fused person estimate (:meth:`FormationSource.set_target`), its slot
angle and the teammates' shared plans as they arrive; the control loop calls :meth:`update` every tick and
shares :attr:`FormationSource.shared_plan` with the teammates. Without a person estimate, or when the
failsafe says hold, it holds the position where it was told to hold (the autopilot brakes to it), facing
the person or turning to search for them.
"""

from __future__ import annotations

import math

import numpy as np

from onboard.formation.mpc import FormationMPC, MpcResult, SharedPlan
from onboard.setpoint import Setpoint

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
        self.search_yaw_rate_rad_s = 0.0
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

    def hold(self, position_ned_m=None, search_yaw_rate_rad_s: float = 0.0) -> None:
        """Hold (failsafe): brake and hold at position_ned_m, or None to resume formation flight. With
        ``search_yaw_rate_rad_s`` != 0 the drone turns on the spot at that rate (looking for the person);
        otherwise it faces the person estimate."""
        self.hold_position_ned_m = None if position_ned_m is None else np.asarray(position_ned_m, dtype=float).copy()
        self.search_yaw_rate_rad_s = float(search_yaw_rate_rad_s) if position_ned_m is not None else 0.0

    @property
    def holding(self) -> bool:
        return self.hold_position_ned_m is not None

    @property
    def shared_plan(self) -> SharedPlan | None:
        """The plan to share with the teammates: the MPC's, or, while holding, the hold point over the horizon
        (the MPC keeps planning in the background then, so that its safety margins stay current)."""
        pl = self.last_plan
        if pl is None or self.hold_position_ned_m is None:
            return pl
        return SharedPlan(pl.drone_id, pl.t0_ns, pl.dt_s, np.tile(self.hold_position_ned_m, (len(pl.positions_ned_m), 1)))

    def _hold_setpoint(self, p: np.ndarray, yaw_rad: float) -> Setpoint:
        hold_at = p if self.hold_position_ned_m is None else self.hold_position_ned_m
        yaw = yaw_rad
        if self.hold_position_ned_m is not None and self.search_yaw_rate_rad_s != 0.0:
            # turn on the spot: the setpoint leads the current heading by half a second of the search rate
            yaw = (yaw_rad + 0.5 * self.search_yaw_rate_rad_s + math.pi) % (2 * math.pi) - math.pi
        elif self._target is not None:
            d = self._target[0] - hold_at
            yaw = math.atan2(d[1], d[0])
        return Setpoint(hold_at.copy(), np.zeros(3), float(yaw))

    def update(self, t_s: float, position_ned_m: np.ndarray, velocity_ned_m_s: np.ndarray, yaw_rad: float) -> Setpoint:
        t_ns = int(round(t_s * 1e9))
        p = np.asarray(position_ned_m, dtype=float)
        if self._target is None:
            return self._hold_setpoint(p, yaw_rad)
        fresh = {i: pl for i, pl in self._plans.items() if (t_ns - pl.t0_ns) * 1e-9 <= self.plan_timeout_s}
        self._plans = fresh
        self._states = {i: st for i, st in self._states.items() if (t_ns - st.t0_ns) * 1e-9 <= self.plan_timeout_s}
        fresh = {**self._states, **fresh}  # a plan, where known, replaces the state
        r = self.mpc.step(t_ns, p, velocity_ned_m_s, self._target[0], self._target[1], self.slot_angle_rad, fresh, self.ground_down_m)
        self.last_result = r
        if self.hold_position_ned_m is not None:
            return self._hold_setpoint(p, yaw_rad)
        accel = (r.plan_velocities_ned_m_s[1] - r.plan_velocities_ned_m_s[0]) / self.mpc.cfg.dt_s
        return Setpoint(
            position_ned_m=r.setpoint_position_ned_m.copy(),
            velocity_ned_m_s=r.setpoint_velocity_ned_m_s.copy(),
            yaw_rad=r.setpoint_yaw_rad,
            gimbal_pitch_rad=float(r.plan_gimbal_pitch_rad[1]),
            acceleration_ned_m_s2=accel,
        )
