"""The agent's mission logic: command and plan validation, and the flight state machine. Pure, no I/O.

:func:`validate_command` / :func:`validate_plan` answer ``None`` (acceptable) or the refusal reason the
agent sends back in its :class:`~shared_msgs.CommandAck`. :class:`Mission` is the state machine: the
agent feeds it accepted commands and vehicle events and executes the :class:`Action` it returns (the
autopilot adapter does the flying); the mission never touches the network or the vehicle itself.

States::

    idle --arm--> armed --takeoff--> takeoff --(airborne at altitude)--> hover
    hover/paused --start (with a plan)--> orbit --pause--> paused
    any airborne --land / failsafe--> landing --(on ground)--> landed (--arm--> armed ...)
    any airborne --return--> returning --(on ground)--> landed
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

from shared_msgs import Command, OrbitPlan
from onboard.config import SafetyConfig
from onboard.orbit import min_slot_separation_m
from onboard.zones import plan_zone_violation

__all__ = ["State", "Action", "Mission", "validate_command", "validate_plan", "message_age_s", "closest_neighbour"]


class State(str, Enum):
    IDLE = "idle"
    ARMED = "armed"
    TAKEOFF = "takeoff"
    HOVER = "hover"
    ORBIT = "orbit"
    PAUSED = "paused"
    LANDING = "landing"
    RETURNING = "returning"
    LANDED = "landed"


AIRBORNE = {State.TAKEOFF, State.HOVER, State.ORBIT, State.PAUSED, State.LANDING, State.RETURNING}
ON_GROUND = {State.IDLE, State.ARMED, State.LANDED}


class Action(str, Enum):
    """What the agent must make the autopilot do after a transition."""

    NONE = "none"
    ARM = "arm"
    TAKEOFF = "takeoff"  # arm if needed, then take off
    START_ORBIT = "start_orbit"  # stream the orbit setpoints, switch to offboard
    PAUSE = "pause"  # offboard hold at the current point
    LAND = "land"
    RETURN = "return"
    HOLD = "hold"  # autopilot Hold (leave offboard)
    DISARM = "disarm"
    RESUME_OFFBOARD = "resume_offboard"  # the autopilot dropped offboard (stream loss): switch back


def message_age_s(t_sent_ns: int, now_ns: int) -> float:
    return (now_ns - t_sent_ns) * 1e-9


def validate_command(cmd: Command, drone_id: str, now_ns: int) -> str | None:
    """Why ``cmd`` must be refused by ``drone_id`` at ``now_ns``, or None.

    The codec has already refused unknown actions, wrong types and non-finite numbers.
    """
    if cmd.target not in ("*", drone_id):
        return f"wrong target {cmd.target!r}: this is {drone_id}"
    if not math.isfinite(cmd.max_age_s) or cmd.max_age_s <= 0:
        return f"bad field max_age_s={cmd.max_age_s}: must be > 0"
    age = message_age_s(cmd.header.t_sent_ns, now_ns)
    if age > cmd.max_age_s:
        return f"stale: sent {age:.1f} s ago, max_age_s={cmd.max_age_s}"
    if age < -2.0:
        return f"bad field header.t_sent_ns: {-age:.1f} s in the future (clocks not synchronised?)"
    for k, v in cmd.params.items():
        if not math.isfinite(v):
            return f"bad field params.{k}={v}"
    if cmd.action == "takeoff" and "altitude_m" in cmd.params:
        alt = cmd.params["altitude_m"]
        if not 0.5 <= alt <= 100:
            return f"bad field params.altitude_m={alt}: takeoff altitude must be in 0.5..100 m"
    return None


def validate_plan(plan: OrbitPlan, drone_id: str, safety: SafetyConfig, now_ns: int, max_age_s: float = 10.0,
                  mode: str | None = None) -> str | None:
    """Why ``plan`` must be refused by ``drone_id``, or None.

    ``mode``: the agent's configured mode ("orbit" / "track"; None = not checked): a plan that says another mode is
    refused (an orbit-mode agent cannot fly a tracking formation: it has no tracker or formation MPC running). The
    plan's geofence and keep-out zones (version 2) are checked by :func:`onboard.zones.plan_zone_violation`."""
    vals = [*plan.center_ned_m, plan.radius_m, plan.altitude_m, plan.angular_speed_rad_s, plan.min_separation_m,
            plan.max_speed_m_s, *plan.phase_offset_rad.values()]
    if plan.gimbal_pitch_rad is not None:
        vals.append(plan.gimbal_pitch_rad)
    if not all(math.isfinite(v) for v in vals):
        return "bad field: non-finite number in plan"
    if plan.mode and mode is not None and plan.mode != mode:
        what = {"track": "a tracking formation", "orbit": "an orbit"}[plan.mode]
        return (f"wrong mode: the plan is {what} (mode {plan.mode!r}) but this agent flies mode {mode!r} "
                f"(its configuration's mode; restart the agent with mode = {plan.mode!r} or send an {mode} plan)")
    if drone_id not in plan.phase_offset_rad:
        return f"wrong target: plan has no phase slot for {drone_id} (slots: {sorted(plan.phase_offset_rad)})"
    if plan.radius_m <= 0:
        return f"bad field radius_m={plan.radius_m}: must be > 0"
    if plan.radius_m > safety.max_radius_m:
        return f"bad field radius_m={plan.radius_m}: above safety.max_radius_m={safety.max_radius_m}"
    if not safety.min_altitude_m <= plan.altitude_m <= safety.max_altitude_m:
        return (f"bad field altitude_m={plan.altitude_m}: outside the band "
                f"{safety.min_altitude_m}..{safety.max_altitude_m} m")
    if plan.angular_speed_rad_s < 0:
        return f"bad field angular_speed_rad_s={plan.angular_speed_rad_s}: must be >= 0 (use direction)"
    speed = plan.radius_m * plan.angular_speed_rad_s
    limit = min(plan.max_speed_m_s, safety.max_speed_m_s)
    if speed > limit:
        return f"bad field angular_speed_rad_s: slot speed {speed:.1f} m/s above the limit {limit:.1f} m/s"
    sep = min_slot_separation_m(plan)
    if sep < plan.min_separation_m:
        return f"bad field phase_offset_rad: slots {sep:.2f} m apart, below min_separation_m={plan.min_separation_m}"
    if plan.gimbal_pitch_rad is not None and not -math.pi / 2 - 1e-9 <= plan.gimbal_pitch_rad <= math.pi / 6:
        return f"bad field gimbal_pitch_rad={plan.gimbal_pitch_rad}: must be in -pi/2..pi/6"
    zone = plan_zone_violation(plan, drone_id)
    if zone is not None:
        return zone
    age = message_age_s(plan.header.t_sent_ns, now_ns)
    if age > max_age_s:
        return f"stale: plan sent {age:.1f} s ago (> {max_age_s} s)"
    return None


def closest_neighbour(own_ned_m, others: dict[str, tuple[tuple[float, float, float], float]], now_s: float,
                      max_age_s: float = 1.0) -> tuple[str, float] | None:
    """The nearest other drone ``(drone_id, distance_m)`` among ``others`` = {id: (position_ned_m, t_s)}
    reported at most ``max_age_s`` ago; None when nobody fresh is known."""
    best: tuple[str, float] | None = None
    for d, (p, t) in others.items():
        if now_s - t > max_age_s:
            continue
        dist = math.dist(own_ned_m, p)
        if best is None or dist < best[1]:
            best = (d, dist)
    return best


@dataclass
class Transition:
    state: State
    action: Action
    refused: str | None = None  #: reason, when the command does not apply in this state


class Mission:
    """The flight state machine of one drone (see the module docstring)."""

    def __init__(self) -> None:
        self.state = State.IDLE
        self.plan: OrbitPlan | None = None
        self.failsafe: str | None = None  #: why the last failsafe fired
        self._armed_seen = False  #: the vehicle reported armed since the arm command

    # --- operator commands -------------------------------------------------------------------------
    def command(self, action: str) -> Transition:
        """Apply an accepted-by-validation command; returns the new state and the action to execute,
        or a refusal when it makes no sense now (the state is then unchanged)."""
        s = self.state
        if self.failsafe and action in ("takeoff", "start") and s in AIRBORNE:
            return self._refuse(f"failsafe active ({self.failsafe}); land first")
        if action == "arm":
            if s in ON_GROUND:
                self._armed_seen = False
                return self._go(State.ARMED, Action.ARM)
            return self._refuse(f"cannot arm in state {s.value}")
        if action == "disarm":
            if s in ON_GROUND:
                return self._go(State.IDLE, Action.DISARM)
            return self._refuse(f"cannot disarm in state {s.value} (airborne); land first")
        if action == "takeoff":
            if s in ON_GROUND:
                self.failsafe = None
                return self._go(State.TAKEOFF, Action.TAKEOFF)
            if s in (State.TAKEOFF, State.HOVER):
                return Transition(s, Action.NONE)  # already up: idempotent
            return self._refuse(f"cannot take off in state {s.value}")
        if action == "start":
            if self.plan is None:
                return self._refuse("no orbit plan received yet; send a plan first")
            if s in (State.HOVER, State.PAUSED, State.TAKEOFF):
                return self._go(State.ORBIT, Action.START_ORBIT)
            if s == State.ORBIT:
                return Transition(s, Action.NONE)
            return self._refuse(f"cannot start the orbit in state {s.value}; take off first")
        if action == "pause":
            if s == State.ORBIT:
                return self._go(State.PAUSED, Action.PAUSE)
            if s == State.PAUSED:
                return Transition(s, Action.NONE)
            return self._refuse(f"nothing to pause in state {s.value}")
        if action == "land":
            if s in AIRBORNE and s != State.LANDING:
                return self._go(State.LANDING, Action.LAND)
            if s == State.LANDING:
                return Transition(s, Action.NONE)
            return self._refuse(f"not airborne (state {s.value})")
        if action == "return":
            if s in AIRBORNE and s not in (State.LANDING, State.RETURNING):
                return self._go(State.RETURNING, Action.RETURN)
            if s == State.RETURNING:
                return Transition(s, Action.NONE)
            return self._refuse(f"cannot return in state {s.value}")
        return self._refuse(f"unknown action {action!r}")

    def set_plan(self, plan: OrbitPlan) -> Transition:
        """A validated plan replaces the previous one; in orbit the controller switches to it."""
        self.plan = plan
        if self.state == State.ORBIT:
            return Transition(self.state, Action.START_ORBIT)
        return Transition(self.state, Action.NONE)

    # --- vehicle events ----------------------------------------------------------------------------
    def vehicle(self, armed: bool, in_air: bool, at_altitude: bool) -> Transition:
        """Follow the vehicle: takeoff done, touchdown, disarm by the autopilot."""
        s = self.state
        if s == State.TAKEOFF and in_air and at_altitude:
            return self._go(State.HOVER, Action.NONE)
        if s in (State.LANDING, State.RETURNING) and not in_air:
            return self._go(State.LANDED, Action.NONE)
        if s == State.ARMED:
            if armed:
                self._armed_seen = True
            elif self._armed_seen:  # armed, then disarmed: the autopilot's preflight auto-disarm
                return self._go(State.IDLE, Action.NONE)
        if s in (State.HOVER, State.ORBIT, State.PAUSED) and not in_air and not armed:
            return self._go(State.LANDED, Action.NONE)  # landed by someone else (RC, autopilot failsafe)
        return Transition(s, Action.NONE)

    def offboard_lost(self, mode: str, may_resume: bool) -> Transition:
        """The autopilot left offboard while we fly the orbit (or hold in offboard).

        ``mode`` is the autopilot's new mode (MAVSDK name). ``may_resume`` (the supervisor's decision: the
        autopilot's offboard-loss failsafe after a stall of ours, policy "resume", budget left): HOLD or RETURN is
        undone (switch back to offboard). Otherwise LAND / RETURN_TO_LAUNCH are followed, and any other mode (HOLD
        without resuming, or a pilot's mode) pauses: the vehicle is left to it until the operator sends ``start``.
        An autopilot LAND is always followed.
        """
        s = self.state
        if s not in (State.ORBIT, State.PAUSED):
            return Transition(s, Action.NONE)
        if mode == "LAND":
            return self._go(State.LANDING, Action.NONE)
        if mode in ("HOLD", "RETURN_TO_LAUNCH") and may_resume:
            return Transition(s, Action.RESUME_OFFBOARD)
        if mode == "RETURN_TO_LAUNCH":
            return self._go(State.RETURNING, Action.NONE)
        return self._go(State.PAUSED, Action.NONE)

    def trigger_failsafe(self, reason: str, action: str) -> Transition:
        """Ground-station loss, low battery, shutdown: ``action`` in land/return/hold, once airborne."""
        s = self.state
        if s not in AIRBORNE or s in (State.LANDING, State.RETURNING):
            return Transition(s, Action.NONE)
        if action == "hold" and s == State.PAUSED:
            return Transition(s, Action.NONE)
        self.failsafe = reason
        if action == "land":
            return self._go(State.LANDING, Action.LAND)
        if action == "return":
            return self._go(State.RETURNING, Action.RETURN)
        return self._go(State.PAUSED, Action.HOLD)

    @property
    def airborne(self) -> bool:
        return self.state in AIRBORNE

    def _go(self, state: State, action: Action) -> Transition:
        self.state = state
        return Transition(state, action)

    def _refuse(self, reason: str) -> Transition:
        return Transition(self.state, Action.NONE, refused=reason)
