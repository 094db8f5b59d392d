"""The agent's vehicle supervisor: the vehicle's events into the mission, and the agent's own failsafes.

:class:`VehicleSupervisor` runs at 10 Hz (:meth:`~VehicleSupervisor.check`) on the autopilot's
:class:`~onboard.agent.telemetry.Telemetry`: it tells the mission when the take-off is done and when the
vehicle touched down, notices the autopilot leaving offboard under the agent and reports it (see below), and
while airborne fires the failsafes configured in ``safety`` (on top of the autopilot's own): ground-station
heartbeat lost, low battery, another drone closer than the plan's separation. What it decides goes back to the
agent through callables: ``failsafe(reason, action)`` (the mission's failsafe path), ``stop_setpoints()`` (drop
the setpoint source), ``resume_offboard()`` (switch the autopilot back to offboard) and ``warn(text)``; it asks
``setpoints_flowing()`` (a setpoint source is set and the stream went out at >= half its rate lately) before
resuming offboard, and ``setpoint_gap_s()`` (the longest gap between two setpoints sent in the last seconds).

Take-off is complete when the autopilot confirmed its take-off (``takeoff_confirmed``, set by the agent once the
vehicle reported its take-off mode), has left that mode (PX4 switches to HOLD when its take-off ends), reports
itself in the air, and is at 0.9 x the asked height above home (or holds still above 1 m: PX4 may use its own
MIS_TAKEOFF_ALT). MAVSDK's ``in_air`` alone turns true during the climb.

The autopilot taking the vehicle out of offboard (``autopilot.on_failsafe``): the mode it went to and whether
the agent's own setpoint stream had stalled (a gap >= 0.8 x ``autopilot.offboard_loss_timeout_s``: the
autopilot's offboard-loss failsafe) are logged and reported as a warning. A stall-caused HOLD or RETURN is
recovered from under "resume" (switch back to offboard once the setpoints flow again, within
``autopilot.resume_wait_s``, at most ``safety.offboard_resumes_per_min`` a minute); otherwise the agent follows:
LAND -> landing, RETURN -> returning, HOLD or anything else (a pilot) -> paused until the operator's ``start``.
PX4 also returns to OFFBOARD by itself when setpoints resume after its offboard-loss failsafe: that is reported
too.
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
                 warn: Callable[[str], None], setpoint_gap_s: Callable[[], float] = lambda: 0.0):
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
        self._setpoint_gap_s = setpoint_gap_s
        self._warn = warn
        #: the autopilot reported its take-off mode after the last take-off command (set by the agent)
        self.takeoff_confirmed = False
        #: the autopilot's current take-over of an offboard flight: (monotonic s, mode, the agent had stalled)
        self._takeover: tuple[float, str, bool] | None = None
        self._stalled = False
        #: every take-over seen: {"t_unix_s", "mode", "stalled", "outcome"} (the agent's health and logs say so)
        self.takeovers: list[dict] = []
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
        # take-off done (see the module doc): confirmed, out of the take-off mode, in the air, at the height
        settled = T.flight_mode == "HOLD" and alt > 1.0 and abs(T.velocity_ned_m_s[2]) < 0.2
        done = (self.takeoff_confirmed and T.flight_mode != "TAKEOFF" and T.landed_state == "in_air"
                and (alt >= 0.9 * self.takeoff_alt_m or settled))
        self.mission.vehicle(T.armed, T.in_air, done)
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
        """Notice the autopilot taking the vehicle out of offboard (its failsafe, or a pilot), report it, and
        resume or follow by ``autopilot.on_failsafe`` (see the module doc)."""
        ap = self.autopilot
        now = time.monotonic()
        changes = list(ap.mode_changes)
        ap.mode_changes.clear()
        if not ap.offboard_active or now - ap.offboard_since_s < 2.0:
            self._takeover = None
            self._stalled = False
            return
        # our own stall beyond the autopilot's offboard-loss timeout: its failsafe fired, whether or not the mode
        # it went to is still (or ever was) visible here (PX4 may return to OFFBOARD within a second when the
        # setpoints resume; measured on PX4 SITL: a 1 s Return that MAVSDK never reported)
        gap = self._setpoint_gap_s()
        stalled_now = gap >= self.cfg.autopilot.offboard_loss_timeout_s
        if stalled_now and not self._stalled and mode == "OFFBOARD" and self._takeover is None:
            away = [new for _, old, new in changes if old == "OFFBOARD" and new != "OFFBOARD"]
            self._report(away[0] if away else f"its offboard-loss action ({self.cfg.autopilot.offboard_loss_action})",
                         True, f"setpoints stalled for {gap:.1f} s (> {self.cfg.autopilot.offboard_loss_timeout_s:.1f} s); "
                               "the vehicle is back in OFFBOARD")
        self._stalled = stalled_now
        if mode == "OFFBOARD":
            if self._takeover is not None:  # PX4 went back to offboard by itself (setpoints resumed)
                t0, m0, stalled = self._takeover
                self._report(m0, stalled, f"autopilot back in OFFBOARD by itself after {now - t0:.1f} s")
                self._takeover = None
            else:
                for t, old, new in changes:  # a short excursion between two checks
                    if old == "OFFBOARD" and new != "OFFBOARD" and not stalled_now:
                        self._report(new, False, "autopilot back in OFFBOARD by itself")
            return
        if mode in ("unknown", ""):
            return
        if self._takeover is None:
            stalled = self._setpoint_gap_s() >= 0.8 * self.cfg.autopilot.offboard_loss_timeout_s
            self._takeover = (now, mode, stalled)
            log.warning("%s: autopilot left offboard for %s%s", self.drone_id, mode,
                        " after a stall of the agent's setpoints (its offboard-loss failsafe)" if stalled else "")
        t0, m0, stalled = self._takeover
        self._resumes = [t for t in self._resumes if now - t < 60.0]
        resumable = (self.cfg.autopilot.on_failsafe == "resume" and stalled and mode in ("HOLD", "RETURN_TO_LAUNCH")
                     and len(self._resumes) < self.cfg.safety.offboard_resumes_per_min
                     and self.mission.state in (State.ORBIT, State.PAUSED))
        if resumable and self._setpoints_flowing():
            tr = self.mission.offboard_lost(mode, may_resume=True)
            if tr.action == Action.RESUME_OFFBOARD:
                self._resumes.append(now)
                self._report(mode, stalled, f"switching back to offboard ({len(self._resumes)} in the last minute)")
                ap.offboard_since_s = now  # no second attempt before this one had time
                self._takeover = None
                self._resume_offboard()
                return
        if resumable and now - t0 < self.cfg.autopilot.resume_wait_s:
            return  # the setpoints are not flowing yet: give them a moment
        before = self.mission.state
        self.mission.offboard_lost(mode, may_resume=False)
        ap.offboard_active = False
        self._takeover = None
        self._report(mode, stalled, f"following it: {before.value} -> {self.mission.state.value}")
        self._stop_setpoints()

    def _report(self, mode: str, stalled: bool, outcome: str) -> None:
        text = (f"autopilot took over in {mode}" + (" (offboard-loss failsafe after a setpoint stall)" if stalled else "")
                + f": {outcome}")
        log.warning("%s: %s", self.drone_id, text)
        self._warn(text)
        self.takeovers.append({"t_unix_s": round(time.time(), 3), "mode": mode, "stalled": stalled, "outcome": outcome})

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
