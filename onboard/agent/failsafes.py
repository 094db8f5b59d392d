"""Track mode's failsafe supervisor wiring: the formation failsafes' decisions, acted on every control step.

:class:`FormationFailsafes` owns the :class:`onboard.formation.failsafe.FormationSupervisor` (built for each
plan when ``track.failsafe.enabled``) and the :class:`~onboard.formation.failsafe.FailsafeLog` every failsafe
of the drone is written to (the formation's, the mission's and the estimator's GPS jumps). Each step
(:meth:`FormationFailsafes.supervise`) it decides from what the drone knows and acts on the
:class:`~onboard.formation.source.FormationSource`: its slot angle, hold / search, or return / land through the
mission (``mission_failsafe(reason, action)``, as the ground-station-loss failsafe). Changes are logged,
counted and kept in the health warnings.
"""

from __future__ import annotations

import logging
import math
from typing import Callable, Mapping

import numpy as np

from onboard.config import FormationFailsafeConfig
from onboard.formation.failsafe import (FailsafeAction, FailsafeConfig, FailsafeInputs, FailsafeLog, FailsafeResponse,
                                        FormationSupervisor, person_seen_s, respond)
from onboard.formation.source import FormationSource
from onboard.tracking.filter import TrackEstimate
from shared_msgs import OrbitPlan, VehicleState

log = logging.getLogger(__name__)

__all__ = ["FormationFailsafes", "supervisor_config"]


def supervisor_config(cfg: FormationFailsafeConfig, plan: OrbitPlan) -> FailsafeConfig:
    """The supervisor's thresholds from the agent's ``track.failsafe`` section and the plan's separation."""
    return FailsafeConfig(
        person_lost_after_s=cfg.person_lost_after_s, teammate_lost_after_s=cfg.teammate_lost_after_s,
        min_separation_margin_m=cfg.separation_margin_m, min_separation_m=plan.min_separation_m,
        min_geofence_margin_m=cfg.geofence_margin_m, max_consecutive_fallbacks=cfg.max_consecutive_fallbacks,
        battery_return_frac=cfg.battery_return_frac, battery_land_frac=cfg.battery_land_frac)


class FormationFailsafes:
    """The formation failsafes of drone ``drone_id`` (see the module doc).

    ``mission_failsafe(reason, action)`` triggers the mission's failsafe path (``action`` "return" / "land");
    ``warn(text)`` adds a health warning.
    """

    def __init__(self, drone_id: str, cfg: FormationFailsafeConfig, mission_failsafe: Callable[[str, str], None],
                 warn: Callable[[str], None]):
        self.drone_id = drone_id
        self.cfg = cfg
        self.log = FailsafeLog(drone_id)  #: every failsafe change of this drone (formation, mission, estimator)
        self.supervisor: FormationSupervisor | None = None  #: None until a plan starts, or when disabled
        self.t_person_seen_s: float | None = None  #: newest accepted detection's capture time (UNIX s)
        self.t_formation_start_s: float | None = None  #: when the supervised formation started (UNIX s)
        self.last_response: FailsafeResponse | None = None
        self._mission_failsafe = mission_failsafe
        self._warn = warn

    @property
    def active(self) -> bool:
        """A supervisor decides (a formation was started with ``track.failsafe.enabled``)."""
        return self.supervisor is not None

    def start(self, plan: OrbitPlan, t_s: float) -> None:
        """A formation starts flying ``plan`` at ``t_s``: a new supervisor (if enabled)."""
        if self.cfg.enabled:
            self.supervisor = FormationSupervisor(self.drone_id, supervisor_config(self.cfg, plan))
            self.t_formation_start_s = t_s

    def inputs(self, t_s: float, own_ned_m: np.ndarray, *, estimate: TrackEstimate | None, person_guess_ned_m,
               src: FormationSource, teammate_states: Mapping[str, VehicleState],
               teammates_seen_s: Mapping[str, float], battery_remaining_frac: float,
               operator_angles_rad: dict[str, float] | None, consecutive_fallbacks: int) -> FailsafeInputs:
        """What the drone knows at ``t_s`` (own_ned_m: its position in the filter's frame); notes the person's
        newest sighting from ``estimate``."""
        f = self.cfg
        if estimate is not None:
            t_seen = estimate.t_last_measurement_ns * 1e-9
            self.t_person_seen_s = t_seen if self.t_person_seen_s is None else max(self.t_person_seen_s, t_seen)
        person = estimate.position_ned_m if estimate is not None else person_guess_ned_m
        r = src.last_result
        fresh = r is not None and (t_s - r.plan.t0_ns * 1e-9) < 1.0
        positions = {d: tuple(st.position_ned_m) for d, st in teammate_states.items()}
        positions[self.drone_id] = tuple(float(v) for v in own_ned_m)
        return FailsafeInputs(
            t_s=t_s, self_id=self.drone_id,
            t_person_seen_s=person_seen_s(self.t_person_seen_s, self.t_formation_start_s or t_s, f.acquire_grace_s,
                                          f.person_lost_after_s),
            teammates_last_seen_s=dict(teammates_seen_s),
            battery_frac=float(battery_remaining_frac),
            predicted_min_separation_m=float(r.min_teammate_distance_m) if fresh else float("inf"),
            predicted_geofence_margin_m=float(r.min_geofence_margin_m) if fresh else float("inf"),
            consecutive_fallbacks=consecutive_fallbacks,
            person_ned_m=tuple(float(v) for v in person),
            positions_ned_m=positions,
            operator_angles_rad=operator_angles_rad,
        )

    def act(self, src: FormationSource, inp: FailsafeInputs, own_ned_m: np.ndarray) -> None:
        """One decision of the supervisor on ``inp``, acted on: ``src``'s slot angle, hold / search, or return /
        land through the mission. Needs :attr:`active`."""
        assert self.supervisor is not None, "no formation started"
        t_s = inp.t_s
        d = self.supervisor.update(inp)
        resp = respond(d, self.drone_id)
        ev = self.log.note(t_s, d)
        if ev is not None:
            (log.info if d.action is FailsafeAction.CONTINUE else log.warning)(
                "%s: formation failsafe -> %s (%s); present %s; slot %.1f deg", self.drone_id, d.action.value,
                "; ".join(d.reasons) or "all well", list(d.present_ids),
                math.degrees(resp.slot_angle_rad) if resp.slot_angle_rad is not None else float("nan"))
            if d.action is not FailsafeAction.CONTINUE:
                self._warn(f"formation failsafe: {d.action.value}: {'; '.join(d.reasons)}")
        if resp.slot_angle_rad is not None:
            src.slot_angle_rad = resp.slot_angle_rad
        if resp.mission_action is not None:
            self._mission_failsafe("; ".join(d.reasons), resp.mission_action)
            return
        search = math.radians(self.cfg.search_yaw_rate_deg_s) if resp.search else 0.0
        if resp.hold and not src.holding:
            src.hold(own_ned_m, search)  # brake and hold where it is now
        elif resp.hold:
            src.search_yaw_rate_rad_s = search
        elif src.holding:
            src.hold(None)
        self.last_response = resp
