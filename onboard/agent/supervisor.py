"""The agent's vehicle supervisor: the vehicle's events into the mission, and the agent's own failsafes.

:class:`VehicleSupervisor` runs at 10 Hz (:meth:`~VehicleSupervisor.check`) on the autopilot's
:class:`~onboard.agent.telemetry.Telemetry`: it tells the mission when the take-off is done and when the
vehicle touched down, notices the autopilot leaving offboard under the agent (PX4's stream-loss HOLD: switch
back, at most ``safety.offboard_resumes_per_min``; LAND / RETURN: follow; anything else: a pilot, pause), and
while airborne fires the failsafes configured in ``safety`` (on top of the autopilot's own): ground-station
heartbeat lost, low battery, another drone closer than the plan's separation. What it decides goes back to the
agent through callables: ``failsafe(reason, action)`` (the mission's failsafe path), ``stop_setpoints()`` (drop
the setpoint source), ``resume_offboard()`` (switch the autopilot back to offboard) and ``warn(text)``; it asks
``setpoints_flowing()`` (a setpoint source is set and the stream went out at >= half its rate lately) before
resuming offboard.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Callable

from onboard.agent.teammates import Teammates
from onboard.config import AgentConfig
from onboard.mission import Action, Mission, State, closest_neighbour

log = logging.getLogger(__name__)

__all__ = ["VehicleSupervisor"]


class VehicleSupervisor:
    """Vehicle events and the ``safety`` failsafes of drone ``cfg.drone_id`` (see the module doc).

    ``autopilot`` is read for its ``telemetry`` record and its offboard bookkeeping (``offboard_active``,
    ``offboard_since_s``, which it also updates).
    """

    def __init__(self, cfg: AgentConfig, mission: Mission, autopilot: Any, teammates: Teammates, *,
                 failsafe: Callable[[str, str], None], stop_setpoints: Callable[[], None],
                 resume_offboard: Callable[[], None], setpoints_flowing: Callable[[], bool],
                 warn: Callable[[str], None]):
        self.drone_id = cfg.drone_id
        self.cfg = cfg
        self.mission = mission
        self.autopilot = autopilot
        self.teammates = teammates
        self.t_last_gcs_s = time.monotonic()  #: the newest ground-station heartbeat (monotonic s)
        self.gcs_seen = False
        self.takeoff_alt_m = cfg.flight.takeoff_altitude_m  #: the altitude of the last take-off asked for
        self._failsafe = failsafe
        self._stop_setpoints = stop_setpoints
        self._resume_offboard = resume_offboard
        self._setpoints_flowing = setpoints_flowing
        self._warn = warn
        self._separation_warned = False
        self._resumes: list[float] = []  #: monotonic times of the offboard resumes in the last minute

    def on_gcs_heartbeat(self) -> None:
        self.t_last_gcs_s = time.monotonic()
        if not self.gcs_seen:
            log.info("%s: ground-station heartbeat received", self.drone_id)
        self.gcs_seen = True

    def check(self) -> None:
        """One supervision step."""
        T = self.autopilot.telemetry
        alt = T.altitude_m
        before = self.mission.state
        # take-off done: at the asked altitude, or the autopilot finished its take-off elsewhere (PX4 may
        # use its own MIS_TAKEOFF_ALT) and holds still in the air
        settled = (T.flight_mode == "HOLD" and T.landed_state == "in_air" and alt > 1.0
                   and abs(T.velocity_ned_m_s[2]) < 0.2)
        self.mission.vehicle(T.armed, T.in_air, alt >= 0.9 * self.takeoff_alt_m or settled)
        if self.mission.state != before:
            log.info("%s: %s -> %s", self.drone_id, before.value, self.mission.state.value)
            if self.mission.state == State.LANDED:
                self._stop_setpoints()
        fs = self.cfg.safety
        self._check_offboard(T.flight_mode)
        if self.mission.airborne:
            silent = time.monotonic() - self.t_last_gcs_s
            if silent > fs.gcs_heartbeat_timeout_s:
                self._failsafe(f"ground-station heartbeat lost for {silent:.1f} s", fs.gcs_loss_action)
            if T.battery_remaining_frac < fs.low_battery_frac:
                self._failsafe(f"low battery {100 * T.battery_remaining_frac:.0f}%", fs.low_battery_action)
            self._check_separation(T.position_ned_m)

    def _check_offboard(self, mode: str) -> None:
        """Notice the autopilot leaving offboard under us (failsafe or pilot) and follow or resume."""
        ap = self.autopilot
        if not ap.offboard_active or mode == "OFFBOARD" or time.monotonic() - ap.offboard_since_s < 2.0:
            return
        now = time.monotonic()
        self._resumes = [t for t in self._resumes if now - t < 60.0]
        may_resume = len(self._resumes) < self.cfg.safety.offboard_resumes_per_min and self._setpoints_flowing()
        before = self.mission.state
        tr = self.mission.offboard_lost(mode, may_resume)
        reason = f"autopilot left offboard for {mode}"
        if tr.action == Action.RESUME_OFFBOARD:
            self._resumes.append(now)
            log.warning("%s: %s: switching back to offboard (%d in the last minute)", self.drone_id, reason,
                        len(self._resumes))
            self._warn(reason + ", resumed")
            ap.offboard_since_s = now  # no second attempt before this one had time
            self._resume_offboard()
            return
        ap.offboard_active = False
        if self.mission.state != before or tr.state in (State.PAUSED, State.LANDING, State.RETURNING):
            log.warning("%s: %s: %s -> %s", self.drone_id, reason, before.value, self.mission.state.value)
            self._warn(reason)
            self._stop_setpoints()

    def _check_separation(self, pos) -> None:
        plan = self.mission.plan
        if pos is None or self.mission.state != State.ORBIT:
            return
        near = closest_neighbour(pos, self.teammates.positions, time.monotonic())
        limit = plan.min_separation_m if plan is not None else 3.0
        if near is None or near[1] >= limit:
            self._separation_warned = False
            return
        reason = f"separation: {near[0]} at {near[1]:.1f} m (< {limit:.1f} m)"
        if self.cfg.safety.separation_action == "warn":
            if not self._separation_warned:
                log.warning("%s: %s", self.drone_id, reason)
                self._warn(reason)
            self._separation_warned = True
        else:
            self._failsafe(reason, self.cfg.safety.separation_action)
