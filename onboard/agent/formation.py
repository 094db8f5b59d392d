"""Track mode's setpoint source: the formation MPC flown around the fused person estimate.

:class:`FormationFlight` builds the :class:`onboard.formation.source.FormationSource` for a plan
(:meth:`~FormationFlight.build_source`: keep ``plan.radius_m`` / ``altitude_m`` from the person at this drone's
slot angle, configured by :class:`onboard.config.TrackConfig`) and flies one control step
(:meth:`~FormationFlight.step`): feed it the fused person estimate and the teammates' states, let the formation
failsafes decide, step the MPC in the filter's frame (own position corrected by the estimated GPS offset) and
return the setpoint in the autopilot's frame; then keep the MPC's statistics and share its plan with the
teammates (``<drone>/formation/plan``), whose plans it avoids (:meth:`~FormationFlight.on_teammate_plan`).
Other sources (a pause's :class:`onboard.setpoint.HoldSource`) are flown as they are.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Callable

import numpy as np

from onboard.agent.failsafes import FormationFailsafes
from onboard.agent.teammates import Teammates
from onboard.agent.tracking import TrackingCapture
from onboard.config import AgentConfig
from onboard.formation.mpc import Cylinder, FormationMPC, MpcConfig, MpcResult, SharedPlan
from onboard.formation.source import FormationSource
from onboard.mission import Mission
from onboard.setpoint import Setpoint, SetpointSource
from onboard.zones import fence_polygon_ne
from onboard.tracking.measurement import PERSON_HEIGHT_PRIOR_M
from shared_msgs import FormationPlan, Message, OrbitPlan, VehicleState, keys
from skycap.frames import yaw_from_quat_wxyz

log = logging.getLogger(__name__)

__all__ = ["FormationFlight", "mpc_config"]


def mpc_config(cfg: AgentConfig, plan: OrbitPlan) -> MpcConfig:
    """The formation MPC's configuration: the agent's ``track`` and ``safety`` sections and the plan (with its
    geofence as the MPC's fence polygon, :func:`onboard.zones.fence_polygon_ne`, and its keep-out zones as
    obstacles)."""
    t = cfg.track
    fence = fence_polygon_ne(plan.geofence) if plan.geofence is not None else ()
    obstacles = tuple(Cylinder(z.north_m, z.east_m, z.radius_m) for z in plan.keepout_zones)
    if plan.geofence is not None:
        # the fence's ceiling bounds the MPC's altitude band too
        max_alt = min(max(cfg.safety.max_altitude_m, plan.altitude_m + 1.0), plan.geofence.max_altitude_m)
    else:
        max_alt = max(cfg.safety.max_altitude_m, plan.altitude_m + 1.0)
    return MpcConfig(geofence_ne_m=fence, obstacles=obstacles, horizon_steps=t.mpc_horizon_steps, dt_s=t.mpc_dt_s,
                     radius_m=plan.radius_m, altitude_m=plan.altitude_m, min_separation_m=plan.min_separation_m,
                     max_speed_h_m_s=min(t.max_speed_h_m_s, plan.max_speed_m_s),
                     min_altitude_m=min(cfg.safety.min_altitude_m, plan.altitude_m),
                     max_altitude_m=max(max_alt, plan.altitude_m + 1e-3),
                     person_keepout_m=min(t.person_keepout_m, 0.75 * plan.radius_m))


class FormationFlight:
    """The formation setpoint source of drone ``cfg.drone_id`` (see the module doc).

    It reads the tracking capture's estimate, the teammates' states, the autopilot's battery (``autopilot``'s
    :class:`~onboard.agent.telemetry.Telemetry`) and the mission's plan (the operator's slot angles), and
    ``publish(topic, msg)`` sends its plan.
    """

    def __init__(self, cfg: AgentConfig, *, tracking: TrackingCapture, failsafes: FormationFailsafes,
                 teammates: Teammates, autopilot: Any, mission: Mission, publish: Callable[[str, Message], None]):
        self.drone_id = cfg.drone_id
        self.cfg = cfg
        self.tracking = tracking
        self.failsafes = failsafes
        self.teammates = teammates
        self.autopilot = autopilot
        self.mission = mission
        self._publish = publish
        #: where the person is assumed before the first track: the plan's centre, half a person above the ground
        self.target_guess_ned_m = np.zeros(3)
        self.mpc_solve_ms: list[float] = []
        self.mpc_fallbacks = 0
        self.consecutive_fallbacks = 0
        self.teammate_plans_received = 0
        self._last_result: MpcResult | None = None

    def build_source(self, plan: OrbitPlan) -> FormationSource:
        """The formation MPC as the setpoint source for ``plan``: keep ``plan.radius_m`` / ``altitude_m`` from
        the person at this drone's slot angle; fly to ``plan.center_ned_m`` (the operator's approximate start
        position of the person) until the filter has a track. Starts the failsafes' supervision. Slow (the
        MPC's solver is built): the agent runs it off its event loop."""
        t0 = time.monotonic()
        src = FormationSource(FormationMPC(self.drone_id, mpc_config(self.cfg, plan)),
                              plan.phase_offset_rad[self.drone_id], ground_down_m=float(plan.center_ned_m[2]),
                              plan_timeout_s=self.cfg.track.plan_timeout_s)
        log.info("%s: formation MPC built in %.1f s", self.drone_id, time.monotonic() - t0)
        self.failsafes.start(plan, time.time())
        guess = np.asarray(plan.center_ned_m, dtype=float) - [0.0, 0.0, 0.5 * PERSON_HEIGHT_PRIOR_M]
        src.set_target(guess, np.zeros(3))
        self.target_guess_ned_m = guess
        return src

    def step(self, src: SetpointSource, t_s: float, st: VehicleState) -> Setpoint:
        """One control step of ``src`` at ``t_s`` (UNIX s) from the own state ``st``."""
        p, v = np.asarray(st.position_ned_m), np.asarray(st.velocity_ned_m_s)
        yaw = yaw_from_quat_wxyz(st.q_world_body)
        if not isinstance(src, FormationSource):  # a pause's hold: flown as it is
            return src.update(t_s, p, v, yaw)
        offset = self.feed(src, t_s)
        if self.failsafes.active:
            self.supervise(src, t_s, p - offset)
        # plan in the filter's frame (own position corrected by the estimated GPS offset), then back to the
        # autopilot's frame for the setpoint
        sp = src.update(t_s, p - offset, v, yaw)
        self.note(src)
        sp.position_ned_m = sp.position_ned_m + offset
        return sp

    def feed(self, src: FormationSource, t_s: float) -> np.ndarray:
        """Before an MPC step: the fused person estimate and the teammates' states; returns this drone's
        estimated position offset (reported - true, (3,): the filter's offset plus a detected GPS jump being
        taken back; zeros without either)."""
        stage = self.tracking.stage
        est = stage.estimate(int(t_s * 1e9))
        if est is not None:
            src.set_target(est.position_ned_m, est.velocity_ned_m_s)
        offset = stage.own_offset(est, int(t_s * 1e9))
        for d, st in self.teammates.states.items():
            src.set_teammate_state(d, st.header.t_measurement_ns, st.position_ned_m, st.velocity_ned_m_s)
        return offset

    def supervise(self, src: FormationSource, t_s: float, own_ned_m: np.ndarray) -> None:
        """One failsafe decision before the MPC step, acted on (:meth:`FormationFailsafes.act`).
        own_ned_m: this drone's position in the filter's frame."""
        plan = self.mission.plan
        inp = self.failsafes.inputs(
            t_s, own_ned_m, estimate=self.tracking.stage.estimate(int(t_s * 1e9)),
            person_guess_ned_m=self.target_guess_ned_m, src=src, teammate_states=self.teammates.states,
            teammates_seen_s=self.teammates.seen_unix_s,
            battery_remaining_frac=self.autopilot.telemetry.battery_remaining_frac,
            operator_angles_rad=dict(plan.phase_offset_rad) if plan is not None else None,
            consecutive_fallbacks=self.consecutive_fallbacks)
        self.failsafes.act(src, inp, own_ned_m)

    def note(self, src: FormationSource) -> None:
        """After an MPC step: its statistics, and its plan shared with the teammates (``formation/plan``)."""
        r = src.last_result
        if r is None or r is self._last_result:
            return
        self._last_result = r
        self.mpc_solve_ms.append(1e3 * r.solve_time_s)
        self.mpc_fallbacks = src.mpc.fallback_count
        self.consecutive_fallbacks = self.consecutive_fallbacks + 1 if r.fallback else 0
        pl = src.shared_plan or r.plan
        msg = FormationPlan(header=FormationPlan.make_header(self.drone_id, int(pl.t0_ns)), t0_ns=int(pl.t0_ns),
                            dt_s=float(pl.dt_s), fallback=bool(r.fallback),
                            positions_ned_m=tuple(float(v) for v in np.asarray(pl.positions_ned_m).reshape(-1)))
        self._publish(keys.FORMATION_PLAN, msg)

    def on_teammate_plan(self, drone_id: str, msg: FormationPlan, src: SetpointSource | None) -> None:
        """Teammate ``drone_id``'s shared MPC plan: avoided by ``src`` when it is a formation source."""
        if drone_id == self.drone_id or not isinstance(src, FormationSource):
            return
        pos = np.asarray(msg.positions_ned_m, dtype=float)
        if pos.size < 6 or pos.size % 3 or not np.all(np.isfinite(pos)):
            log.warning("%s: ignoring a malformed formation plan from %s (%d floats)", self.drone_id, drone_id, pos.size)
            return
        src.set_teammate_plan(SharedPlan(drone_id, int(msg.t0_ns), float(msg.dt_s), pos.reshape(-1, 3)))
        self.teammate_plans_received += 1

    def stats(self) -> dict:
        """The formation's part of the flight statistics."""
        return {"mpc_solve_ms": [round(v, 3) for v in self.mpc_solve_ms], "mpc_fallbacks": int(self.mpc_fallbacks),
                "teammate_plans_received": int(self.teammate_plans_received)}
