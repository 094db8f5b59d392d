"""The onboard agent: one process per drone, on its companion computer.

It connects to its autopilot (:class:`onboard.agent.autopilot.MavsdkAutopilot`, MAVSDK as a companion
computer), joins the fleet over Zenoh (:class:`comms.transport.Transport`), takes plans and commands
from the ground station and answers each with a :class:`~shared_msgs.CommandAck`, flies its slot of the
orbit by streaming offboard setpoints, watches the ground-station heartbeat and the battery, and records
everything it sees to its MCAP file (:mod:`flightdata.recorder`).

Parts (so that perception, tracking and formation control plug in without rewrites):

* ``mission`` -- :class:`onboard.mission.Mission`, the pure state machine; validation in
  :func:`onboard.mission.validate_command` / :func:`~onboard.mission.validate_plan`.
* ``source`` -- the current :class:`onboard.orbit.SetpointSource` (``OrbitController`` now, a formation
  MPC later), asked for one setpoint per control tick.
* ``perception`` -- a list of :class:`PerceptionStage`; each camera frame goes through them in order and
  what they return is published and recorded (a detector, a keypoint model, a target tracker).
* ``autopilot`` -- the thin MAVSDK adapter; ``bus`` -- the Zenoh transport; ``recorder`` -- the MCAP writer.

Track mode (``mode = "track"``): the tracking stage fuses own and teammates' detections, the formation MPC
flies around the fused person estimate, and before every MPC step the formation failsafes
(:class:`onboard.formation.failsafe.FormationSupervisor`, configured by ``track.failsafe``) decide: re-space
when a teammate falls silent (no state or plan for ``teammate_lost_after_s``) or joins, brake and hold when a
separation / geofence breach is predicted or the MPC keeps falling back, hold and turn to search when the
person is lost, return / land on low battery (through the mission, like the ground-station-loss failsafe).
Every change is logged, counted, kept in the health warnings and written to ``<drone>.track.json``
(``failsafe_events``, ``failsafe_counts``) with the malformed-detection and network-fault counters.

Loops (asyncio, one thread + MAVSDK's and Zenoh's own): the control loop (``rates.setpoint_hz``), the
supervisor (10 Hz: vehicle events, failsafes, health heartbeat) and the telemetry callbacks (50 Hz:
record state, publish it at ``rates.state_publish_hz``).
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import signal
import time
from collections import deque
from typing import Any, Protocol

import msgspec
import numpy as np

from shared_msgs import (
    CameraFrame,
    CameraInfo,
    Command,
    CommandAck,
    Detections,
    FormationPlan,
    Health,
    Keypoints2D,
    Message,
    OrbitPlan,
    VehicleState,
    encode,
    keys,
    stamp_sent,
)
from onboard.config import AgentConfig
from skycap.frames import yaw_from_quat_wxyz
from flightdata.recorder import channel_name
from onboard.mission import Action, Mission, State, closest_neighbour, validate_command, validate_plan
from onboard.orbit import HoldSource, OrbitController, Setpoint, SetpointSource

log = logging.getLogger(__name__)

__all__ = ["Agent", "PerceptionStage", "RateMeter"]


class PerceptionStage(Protocol):
    """One step of the onboard perception pipeline (detector, keypoints, tracker ...).

    ``process(frame, info, state)`` gets a camera frame, the latest camera info and the vehicle state at
    hand, and returns ``(topic, message)`` pairs to publish on this drone's keys and record.
    """

    name: str

    def process(self, frame: CameraFrame, info: CameraInfo | None, state: VehicleState | None) -> list[tuple[str, Message]]: ...


class RateMeter:
    """Events per second over a sliding window (for the health report)."""

    def __init__(self, window_s: float = 2.0):
        self.window_s = window_s
        self._t: deque[float] = deque()

    def tick(self, t_s: float | None = None) -> None:
        self._t.append(time.monotonic() if t_s is None else t_s)

    def rate_hz(self, t_s: float | None = None) -> float:
        now = time.monotonic() if t_s is None else t_s
        while self._t and self._t[0] < now - self.window_s:
            self._t.popleft()
        return len(self._t) / self.window_s


class Agent:
    """One drone's agent. ``await agent.run(stop)`` until ``stop`` is set (SIGTERM), then shut down cleanly."""

    def __init__(self, cfg: AgentConfig, bus: Any, autopilot: Any, recorder: Any = None,
                 perception: list[PerceptionStage] | None = None):
        self.cfg = cfg.validate()
        self.id = cfg.drone_id
        self.bus = bus
        self.autopilot = autopilot
        self.recorder = recorder
        self.perception: list[PerceptionStage] = list(perception or [])
        self.mission = Mission()
        self.source: SetpointSource | None = None
        self.last_setpoint: Setpoint | None = None
        self.state: VehicleState | None = None
        self.camera_info: CameraInfo | None = None
        self.t_last_gcs_s = time.monotonic()
        self.gcs_seen = False
        self.rates = {k: RateMeter() for k in ("setpoint", "state", "frame", "keypoints")}
        self._act_lock = asyncio.Lock()
        self._tasks: list[asyncio.Task] = []
        self._subs: list[Any] = []
        self._last_state_pub_s = 0.0
        self._cpu = (time.monotonic(), time.process_time())
        self.warnings: list[str] = []
        #: latest positions of the other drones {drone_id: (position_ned_m, monotonic receive time)}
        self.neighbours: dict[str, tuple[tuple[float, float, float], float]] = {}
        self._separation_warned = False
        self._gimbal_sent: tuple[float, float] | None = None
        self._resumes: list[float] = []
        self.acks: list[CommandAck] = []  # for tests and the health report
        #: latest states of the other drones {drone_id: VehicleState} (the formation MPC avoids them)
        self.neighbour_states: dict[str, VehicleState] = {}
        #: active capture (cfg.mode == "track"): the tracking stage and the formation MPC's statistics
        self.tracking = None
        self.mpc_solve_ms: list[float] = []
        self.mpc_fallbacks = 0
        self.teammate_plans_received = 0
        self._last_target_pub_s = 0.0
        #: track mode: the formation failsafes (onboard.formation.failsafe) and what they decided
        self.teammate_seen_s: dict[str, float] = {}  #: newest state/plan per teammate (UNIX s of receipt)
        self.supervisor = None
        self.failsafe_log = None
        self._t_person_seen_s: float | None = None
        self._t_formation_start_s: float | None = None
        self._consecutive_fallbacks = 0
        self._fs_response = None
        self.detector_worker = None  #: track mode with detections = "onnx": the ONNX detector's worker thread
        self._loop: asyncio.AbstractEventLoop | None = None
        if cfg.mode == "track":
            from onboard.tracking.stage import TrackingStage, TrackingStageConfig

            from onboard.tracking.filter import TrackerConfig
            from onboard.tracking.measurement import MeasurementConfig
            from onboard.tracking.roi import RoiConfig

            self.tracking = TrackingStage(self.id, TrackingStageConfig(
                # the own-position offset's prior: this drone's positioning grade (GPS ~1 m, RTK ~5 cm)
                tracker=TrackerConfig(offset_sigma_m=cfg.track.camera_position_sigma_m,
                                      velocity_sigma_m_s=cfg.track.person_velocity_sigma_m_s),
                measurement=MeasurementConfig(person_height_m=cfg.track.person_height_m),
                roi=RoiConfig(person_height_m=cfg.track.person_height_m),
                camera_position_sigma_m=cfg.track.camera_position_sigma_m,
                camera_rotation_sigma_rad=cfg.track.camera_rotation_sigma_rad))
            self.rates["detections"] = RateMeter()
            if cfg.track.detections == "onnx":
                from onboard.detector.detector import DetectorConfig, PersonDetector
                from onboard.detector.stage import DetectionWorker

                self.detector_worker = DetectionWorker(
                    self.id, PersonDetector(DetectorConfig(model=cfg.track.detector_model, threads=cfg.track.detector_threads)),
                    self._deliver_detections)
            from onboard.formation.failsafe import FailsafeLog

            self.failsafe_log = FailsafeLog(self.id)
        autopilot.on_state = self._on_state

    # --- keys ----------------------------------------------------------------------------------------
    def key(self, topic: str) -> str:
        return keys.drone_key(self.cfg.fleet, self.id, topic)

    # --- recording and publishing -------------------------------------------------------------------
    def _record(self, key: str, data: bytes, log_time_ns: int | None = None) -> None:
        """Record bytes as sent/received on the recorder channel of ``key`` (``state``, ``gcs/cmd`` ...)."""
        if self.recorder is None:
            return
        try:
            self.recorder.record(channel_name(key, self.id), data, log_time_ns)
        except Exception as e:
            if not getattr(self, "_record_failed", False):
                log.error("%s: recording on %s failed: %s", self.id, key, e)
                self._record_failed = True

    def publish(self, topic: str, msg: Message, latch: bool = False) -> None:
        key = self.key(topic)
        try:
            data = self.bus.publish(key, msg, latch=latch)
        except Exception as e:  # a dead network must not stop the flight
            log.warning("%s: publish on %s failed: %s", self.id, key, e)
            data = encode(stamp_sent(msg))
        self._record(key, data)

    def ack(self, command_id: str, result: str, reason: str = "") -> None:
        a = CommandAck(header=CommandAck.make_header(self.id), command_id=command_id, result=result, reason=reason)
        self.acks.append(a)
        (log.warning if result in ("refused", "failed") else log.info)(
            "%s: %s %s%s", self.id, result, command_id, f": {reason}" if reason else "")
        self.publish(keys.ACK, a)

    # --- inputs (run on the loop) -------------------------------------------------------------------
    def _on_state(self, st: VehicleState) -> None:
        self.state = st
        self.rates["state"].tick()
        if self.tracking is not None and self.cfg.track.gps_jump_threshold_m > 0:
            self._check_gps_jump(st)
        if self.tracking is not None and st.landed_state == "on_ground" and np.isfinite(st.position_ned_m[2]):
            self.tracking.set_own_ground(st.position_ned_m[2])  # the take-off ground in the reported frame
        if self.tracking is not None and self.cfg.track.camera_cov_from_state:
            var = np.asarray(st.position_cov_m2, dtype=float)
            if var.shape == (3,) and np.all(np.isfinite(var)) and np.all(var > 0):
                self.tracking.set_own_position_cov(var)
        if self.recorder is not None:
            self._record(self.key(keys.STATE), encode(stamp_sent(st)), st.header.t_measurement_ns)
        t = time.monotonic()
        if t - self._last_state_pub_s >= 1.0 / self.cfg.rates.state_publish_hz - 1e-3:
            self._last_state_pub_s = t
            try:
                self.bus.publish(self.key(keys.STATE), st)
            except Exception as e:
                log.debug("state publish failed: %s", e)

    def _check_gps_jump(self, st: VehicleState) -> None:
        """Track mode: notice a jump of the reported position (a step the reported velocity does not explain,
        between samples <= 0.5 s apart); log and count it, and hand it to the tracking stage, which takes it back
        from the own camera poses and the planning position (relaxing over ``track.gps_jump_relax_s`` while the
        filter's offset takes over), so that the drone stays in the fleet's frame."""
        t_ns = int(st.header.t_measurement_ns)
        p = np.asarray(st.position_ned_m, dtype=float)
        v = np.asarray(st.velocity_ned_m_s, dtype=float)
        prev, self._jump_prev = getattr(self, "_jump_prev", None), (t_ns, p, v)
        if prev is None or not 0 < (t_ns - prev[0]) * 1e-9 <= 0.5:
            return
        dt_s = (t_ns - prev[0]) * 1e-9
        v_mean = 0.5 * (prev[2] + v)
        step = p - (prev[1] + v_mean * dt_s)
        size = float(np.linalg.norm(step))
        # receive-time stamps: a delayed sample followed by a burst makes dt too long; tolerate the whole travel
        # over dt on top of the threshold so that such bursts never look like jumps
        if size <= self.cfg.track.gps_jump_threshold_m + float(np.linalg.norm(v_mean)) * dt_s:
            return
        t = self.cfg.track
        self.tracking.set_position_step(step, t_ns, t.gps_jump_relax_s)
        reason = (f"reported position jumped {size:.2f} m ({', '.join(f'{x:+.2f}' for x in step)} NED) against its "
                  f"velocity: taken back from the own poses, relaxing over {t.gps_jump_relax_s:.0f} s")
        log.warning("%s: GPS jump: %s", self.id, reason)
        self.warnings.append("GPS jump " + reason)
        if self.failsafe_log is not None:
            self.failsafe_log.add(time.time(), "gps_jump", [reason], source="estimator")

    def on_gcs_health(self, rx) -> None:
        self.t_last_gcs_s = time.monotonic()
        if not self.gcs_seen:
            log.info("%s: ground-station heartbeat received", self.id)
        self.gcs_seen = True

    def on_neighbour_state(self, rx) -> None:
        node = keys.parse_key(rx.key)[1]
        if node != self.id:
            self.neighbours[node] = (rx.msg.position_ned_m, time.monotonic())
            self.neighbour_states[node] = rx.msg
            self.teammate_seen_s[node] = time.time()

    def on_detections(self, rx) -> None:
        """A teammate's shared detections (track mode): fused into this drone's filter."""
        if self.tracking is None or not isinstance(rx.msg, Detections):
            return
        if keys.parse_key(rx.key)[1] == self.id:
            return  # our own, already fused
        self._record(rx.key, rx.data, rx.t_received_ns)
        try:
            self.tracking.on_teammate_detections(rx.msg)
        except Exception:
            log.exception("%s: fusing %s's detections failed", self.id, rx.msg.header.sender_id)

    def on_command(self, rx) -> None:
        self._record(rx.key, rx.data, rx.t_received_ns)
        cmd: Command = rx.msg
        if cmd.target not in ("*", self.id):
            return  # another drone's command: its agent answers
        reason = validate_command(cmd, self.id, rx.t_received_ns)
        if reason is not None:
            self.ack(cmd.command_id, "refused", reason)
            return
        tr = self.mission.command(cmd.action)
        if tr.refused:
            self.ack(cmd.command_id, "refused", tr.refused)
            return
        self.ack(cmd.command_id, "accepted")
        self._spawn(self._execute(tr.action, cmd.command_id, cmd.params), f"cmd:{cmd.action}")

    def on_plan(self, rx) -> None:
        self._record(rx.key, rx.data, rx.t_received_ns)
        plan: OrbitPlan = rx.msg
        if self.mission.plan is not None and plan.plan_id == self.mission.plan.plan_id and \
                plan.header.t_sent_ns == self.mission.plan.header.t_sent_ns:
            return  # the same plan again (live + query)
        reason = validate_plan(plan, self.id, self.cfg.safety, rx.t_received_ns)
        if reason is not None:
            self.ack(plan.plan_id, "refused", reason)
            return
        if plan.start_time_ns == 0:
            plan = msgspec.structs.replace(plan, start_time_ns=rx.t_received_ns)
        tr = self.mission.set_plan(plan)
        self.ack(plan.plan_id, "accepted")
        if tr.action == Action.START_ORBIT:
            self._spawn(self._execute(Action.START_ORBIT, plan.plan_id, {}), "plan")

    def on_camera(self, rx) -> None:
        msg = rx.msg
        if self.cfg.record_camera or not isinstance(msg, CameraFrame):  # frames taken only for the detector: not kept
            self._record(rx.key, rx.data, rx.t_received_ns)
        if isinstance(msg, CameraInfo):
            self.camera_info = msg
            if self.tracking is not None:
                self.tracking.set_camera_info(msg)
        elif isinstance(msg, Detections):
            if self.tracking is not None and self.detector_worker is None and rx.key == self.key(keys.SIM_DETECTIONS):
                self._own_detections(msg, None)
        elif isinstance(msg, CameraFrame):
            self.rates["frame"].tick()
            if self.detector_worker is not None and self.tracking is not None:
                try:
                    plan = self.tracking.plan_for(msg.header.t_measurement_ns, msg.T_world_cam)
                    if plan is not None:
                        self.detector_worker.submit(msg, plan.mode, plan.roi_px, context=plan)
                except Exception:
                    log.exception("%s: planning the detection failed", self.id)
            for stage in self.perception:
                try:
                    for topic, out in stage.process(msg, self.camera_info, self.state):
                        self.publish(topic, out)
                except Exception:
                    log.exception("%s: perception stage %s failed", self.id, getattr(stage, "name", stage))
        elif isinstance(msg, Keypoints2D):
            self.rates["keypoints"].tick()

    def _own_detections(self, msg: Detections, plan) -> None:
        """This drone's detections (the simulator's, or the ONNX detector's with the plan it ran with) ->
        the tracking stage -> shared with the teammates."""
        self.rates["detections"].tick()
        try:
            out = self.tracking.on_own_detections(msg, plan)
            if out is not None:  # None: malformed, ignored and counted by the stage
                self.publish(keys.DETECTIONS, out)
        except Exception:
            log.exception("%s: tracking stage failed", self.id)

    def _deliver_detections(self, det: Detections, plan) -> None:
        """Called on the detector's worker thread: hop to the agent's event loop."""
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self._own_detections, det, plan)

    # --- actions ------------------------------------------------------------------------------------
    def _spawn(self, coro, name: str) -> None:
        t = asyncio.get_running_loop().create_task(coro, name=name)
        self._tasks.append(t)
        t.add_done_callback(lambda tt: self._tasks.remove(tt) if tt in self._tasks else None)

    async def _execute(self, action: Action, command_id: str, params: dict[str, float]) -> None:
        ap = self.autopilot
        async with self._act_lock:
            try:
                if action == Action.ARM:
                    await ap.wait_healthy(self.cfg.flight.health_timeout_s)
                    await ap.arm()
                elif action == Action.TAKEOFF:
                    await ap.wait_healthy(self.cfg.flight.health_timeout_s)
                    if not ap.telemetry["armed"]:
                        await ap.arm()
                    self._takeoff_alt_m = float(params.get("altitude_m", self.cfg.flight.takeoff_altitude_m))
                    await ap.takeoff(self._takeoff_alt_m)
                elif action == Action.START_ORBIT:
                    await self._start_orbit()
                elif action == Action.PAUSE:
                    st = self.state
                    if st is not None:
                        self.source = HoldSource(st.position_ned_m, yaw_from_quat_wxyz(st.q_world_body))
                elif action in (Action.LAND, Action.RETURN, Action.HOLD):
                    self.source = None
                    await {Action.LAND: ap.land, Action.RETURN: ap.return_to_launch, Action.HOLD: ap.hold}[action]()
                elif action == Action.DISARM:
                    await ap.disarm()
            except Exception as e:
                log.error("%s: %s failed: %s", self.id, action.value, e)
                self.ack(command_id, "failed", str(e))
                if action in (Action.ARM, Action.TAKEOFF):
                    self.mission.state = State.IDLE if not ap.telemetry["armed"] else State.ARMED
                return
            self.ack(command_id, "completed")

    async def _start_orbit(self) -> None:
        plan = self.mission.plan
        st = self.state
        if plan is None or st is None:
            raise RuntimeError("no plan or no vehicle state yet")
        if self.cfg.mode == "track":
            self.source = await asyncio.to_thread(self._formation_source, plan)
        else:
            self.source = OrbitController(plan, self.id, self.cfg.flight.approach_speed_m_s,
                                          self.cfg.flight.approach_climb_m_s)
        if not self.autopilot.offboard_active:
            # PX4 refuses offboard without a setpoint stream: let the control loop stream first.
            await asyncio.sleep(max(1.0, 10.0 / self.cfg.rates.setpoint_hz))
            await self.autopilot.start_offboard()

    def _formation_source(self, plan: OrbitPlan):
        """The formation MPC as the setpoint source (track mode): keep ``plan.radius_m`` / ``altitude_m``
        from the person at this drone's slot angle; fly to ``plan.center_ned_m`` (the operator's approximate
        start position of the person) until the filter has a track."""
        from onboard.formation.mpc import FormationMPC, MpcConfig
        from onboard.formation.source import FormationSource
        from onboard.tracking.measurement import PERSON_HEIGHT_PRIOR_M

        t = self.cfg.track
        mc = MpcConfig(horizon_steps=t.mpc_horizon_steps, dt_s=t.mpc_dt_s, radius_m=plan.radius_m,
                       altitude_m=plan.altitude_m, min_separation_m=plan.min_separation_m,
                       max_speed_h_m_s=min(t.max_speed_h_m_s, plan.max_speed_m_s),
                       min_altitude_m=min(self.cfg.safety.min_altitude_m, plan.altitude_m),
                       max_altitude_m=max(self.cfg.safety.max_altitude_m, plan.altitude_m + 1.0),
                       person_keepout_m=min(t.person_keepout_m, 0.75 * plan.radius_m))
        t0 = time.monotonic()
        src = FormationSource(FormationMPC(self.id, mc), plan.phase_offset_rad[self.id],
                              ground_down_m=float(plan.center_ned_m[2]), plan_timeout_s=t.plan_timeout_s)
        log.info("%s: formation MPC built in %.1f s", self.id, time.monotonic() - t0)
        if t.failsafe.enabled:
            from onboard.formation.failsafe import FailsafeConfig, FormationSupervisor

            f = t.failsafe
            self.supervisor = FormationSupervisor(self.id, FailsafeConfig(
                person_lost_after_s=f.person_lost_after_s, teammate_lost_after_s=f.teammate_lost_after_s,
                min_separation_margin_m=f.separation_margin_m, min_separation_m=plan.min_separation_m,
                min_geofence_margin_m=f.geofence_margin_m, max_consecutive_fallbacks=f.max_consecutive_fallbacks,
                battery_return_frac=f.battery_return_frac, battery_land_frac=f.battery_land_frac))
            self._t_formation_start_s = time.time()
        guess = np.asarray(plan.center_ned_m, dtype=float) - [0.0, 0.0, 0.5 * PERSON_HEIGHT_PRIOR_M]
        src.set_target(guess, np.zeros(3))
        self._target_guess = guess
        return src

    def _feed_formation(self, src, t_s: float) -> np.ndarray:
        """Before an MPC step: the fused person estimate and the teammates' states; returns this drone's
        estimated position offset (reported - true, (3,): the filter's offset plus a detected GPS jump being
        taken back; zeros without either)."""
        offset = np.zeros(3)
        if self.tracking is not None:
            est = self.tracking.estimate(int(t_s * 1e9))
            if est is not None:
                src.set_target(est.position_ned_m, est.velocity_ned_m_s)
            offset = self.tracking.own_offset(est, int(t_s * 1e9))
        for d, st in self.neighbour_states.items():
            src.set_teammate_state(d, st.header.t_measurement_ns, st.position_ned_m, st.velocity_ned_m_s)
        return offset

    def _supervise_formation(self, src, t_s: float, own_ned_m: np.ndarray) -> None:
        """One failsafe decision (track mode) before the MPC step, and act on it: slot angle, hold / search,
        or return / land through the mission. Changes are logged, counted and kept in ``failsafe_log``.
        own_ned_m: this drone's position in the filter's frame."""
        from onboard.formation.failsafe import FailsafeAction, FailsafeInputs, person_seen_s, respond

        sup, f = self.supervisor, self.cfg.track.failsafe
        est = self.tracking.estimate(int(t_s * 1e9)) if self.tracking is not None else None
        if est is not None:
            t_seen = est.t_last_measurement_ns * 1e-9
            self._t_person_seen_s = t_seen if self._t_person_seen_s is None else max(self._t_person_seen_s, t_seen)
        person = est.position_ned_m if est is not None else getattr(self, "_target_guess", np.zeros(3))
        r = src.last_result
        fresh = r is not None and (t_s - r.plan.t0_ns * 1e-9) < 1.0
        positions = {d: tuple(st.position_ned_m) for d, st in self.neighbour_states.items()}
        positions[self.id] = tuple(float(v) for v in own_ned_m)
        plan = self.mission.plan
        inp = FailsafeInputs(
            t_s=t_s, self_id=self.id,
            t_person_seen_s=person_seen_s(self._t_person_seen_s, self._t_formation_start_s or t_s, f.acquire_grace_s,
                                          f.person_lost_after_s),
            teammates_last_seen_s=dict(self.teammate_seen_s),
            battery_frac=float(self.autopilot.telemetry.get("battery_frac", 1.0)),
            predicted_min_separation_m=float(r.min_teammate_distance_m) if fresh else float("inf"),
            predicted_geofence_margin_m=float(r.min_geofence_margin_m) if fresh else float("inf"),
            consecutive_fallbacks=self._consecutive_fallbacks,
            person_ned_m=tuple(float(v) for v in person),
            positions_ned_m=positions,
            operator_angles_rad=dict(plan.phase_offset_rad) if plan is not None else None,
        )
        d = sup.update(inp)
        resp = respond(d, self.id)
        ev = self.failsafe_log.note(t_s, d)
        if ev is not None:
            (log.info if d.action is FailsafeAction.CONTINUE else log.warning)(
                "%s: formation failsafe -> %s (%s); present %s; slot %.1f deg", self.id, d.action.value,
                "; ".join(d.reasons) or "all well", list(d.present_ids),
                math.degrees(resp.slot_angle_rad) if resp.slot_angle_rad is not None else float("nan"))
            if d.action is not FailsafeAction.CONTINUE:
                self.warnings.append(f"formation failsafe: {d.action.value}: {'; '.join(d.reasons)}")
        if resp.slot_angle_rad is not None:
            src.slot_angle_rad = resp.slot_angle_rad
        if resp.mission_action is not None:
            self._failsafe("; ".join(d.reasons), resp.mission_action)
            return
        search = math.radians(f.search_yaw_rate_deg_s) if resp.search else 0.0
        if resp.hold and not src.holding:
            src.hold(own_ned_m, search)  # brake and hold where it is now
        elif resp.hold:
            src.search_yaw_rate_rad_s = search
        elif src.holding:
            src.hold(None)
        self._fs_response = resp

    def _note_formation(self, src) -> None:
        """After an MPC step: its statistics, and its plan shared with the teammates (``formation/plan``)."""
        r = src.last_result
        if r is not None and r is not getattr(self, "_last_mpc_result", None):
            self._last_mpc_result = r
            self.mpc_solve_ms.append(1e3 * r.solve_time_s)
            self.mpc_fallbacks = src.mpc.fallback_count
            self._consecutive_fallbacks = self._consecutive_fallbacks + 1 if r.fallback else 0
            pl = getattr(src, "shared_plan", None) or r.plan
            msg = FormationPlan(header=FormationPlan.make_header(self.id, int(pl.t0_ns)), t0_ns=int(pl.t0_ns),
                                dt_s=float(pl.dt_s), fallback=bool(r.fallback),
                                positions_ned_m=tuple(float(v) for v in np.asarray(pl.positions_ned_m).reshape(-1)))
            self.publish(keys.FORMATION_PLAN, msg)

    def on_formation_plan(self, rx) -> None:
        """A teammate's shared MPC plan (track mode): avoided by this drone's MPC."""
        from onboard.formation.mpc import SharedPlan

        msg = rx.msg
        node = keys.parse_key(rx.key)[1]
        src = self.source
        if node == self.id or not isinstance(msg, FormationPlan) or not hasattr(src, "set_teammate_plan"):
            return
        pos = np.asarray(msg.positions_ned_m, dtype=float)
        if pos.size < 6 or pos.size % 3 or not np.all(np.isfinite(pos)):
            log.warning("%s: ignoring a malformed formation plan from %s (%d floats)", self.id, node, pos.size)
            return
        src.set_teammate_plan(SharedPlan(node, int(msg.t0_ns), float(msg.dt_s), pos.reshape(-1, 3)))
        self.teammate_plans_received += 1

    def publish_target(self) -> None:
        if self.tracking is None:
            return
        msg = self.tracking.target_message(time.time_ns())
        if msg is not None:
            self.publish(keys.TARGET, msg)

    def tracking_stats(self) -> dict:
        """What the flight summary needs from this agent's tracking (written next to its recording)."""
        tr = self.tracking
        return {
            "drone_id": self.id,
            "mode": self.cfg.mode,
            "detections_source": ("onnx:" + self.cfg.track.detector_model) if self.detector_worker else self.cfg.track.detections,
            "detector": None if self.detector_worker is None else self.detector_worker.stats(),
            "mpc_solve_ms": [round(v, 3) for v in self.mpc_solve_ms],
            "mpc_fallbacks": int(self.mpc_fallbacks),
            "teammate_plans_received": int(self.teammate_plans_received),
            "offset_log": [] if tr is None else [list(r) for r in tr.offset_log],
            "counts": {} if tr is None else dict(tr.counts),
            "filter_stats": {} if tr is None else dict(vars(tr.filter.stats)),
            "failsafe_events": [] if self.failsafe_log is None else list(self.failsafe_log.events),
            "failsafe_counts": {} if self.failsafe_log is None else dict(self.failsafe_log.counts),
            "malformed_detections": self.malformed_detections(),
            "transport": self.transport_counts(),
        }

    def _detection_subs(self) -> list:
        det_topics = (keys.DETECTIONS, keys.SIM_DETECTIONS)
        return [s for s in self._subs if any(getattr(s, "key_expr", "").endswith("/" + t) for t in det_topics)]

    def malformed_detections(self) -> dict:
        """Detections ignored as malformed: refused by the codec on receipt (NaN/inf, wrong array lengths,
        undecodable), refused by the tracking stage (inconsistent boxes, non-rigid pose ...), and
        non-finite measurements the filter refused; ``total`` = their sum."""
        codec = sum(int(getattr(s.stats, "malformed", 0)) for s in self._detection_subs())
        tr = self.tracking
        content = int(tr.counts.get("malformed_detections", 0)) if tr is not None else 0
        nonfinite = int(tr.filter.stats.rejected_nonfinite) if tr is not None else 0
        return {"refused_by_codec": codec, "invalid_content": content, "nonfinite_measurements": nonfinite,
                "total": codec + content + nonfinite}

    def transport_counts(self) -> dict:
        """Receive counters over all subscriptions (with the simulated fault layer's drops and delays)."""
        out = {"received": 0, "malformed": 0, "fault_judged": 0, "fault_dropped": 0, "fault_delayed": 0}
        for s in self._subs:
            st = getattr(s, "stats", None)
            for k in out:
                out[k] += int(getattr(st, k, 0) or 0)
        return out

    # --- loops ----------------------------------------------------------------------------------------
    async def control_loop(self) -> None:
        period = 1.0 / self.cfg.rates.setpoint_hz
        t_next = time.monotonic()
        while True:
            t_next += period
            src, st = self.source, self.state
            if src is not None and st is not None:
                try:
                    t_s = time.time()
                    formation = hasattr(src, "set_teammate_state")
                    offset = self._feed_formation(src, t_s) if formation else np.zeros(3)
                    if formation and self.supervisor is not None:
                        self._supervise_formation(src, t_s, np.asarray(st.position_ned_m) - offset)
                    # track mode: plan in the filter's frame (own position corrected by the estimated GPS
                    # offset), then back to the autopilot's frame for the setpoint
                    sp = src.update(t_s, np.asarray(st.position_ned_m) - offset, np.asarray(st.velocity_ned_m_s),
                                    yaw_from_quat_wxyz(st.q_world_body))
                    if formation:
                        self._note_formation(src)
                        sp.position_ned_m = sp.position_ned_m + offset
                    await self.autopilot.set_setpoint(sp)
                    self.last_setpoint = sp
                    self.rates["setpoint"].tick()
                except Exception as e:
                    log.warning("%s: setpoint failed: %s", self.id, e)
                else:
                    await self._point_gimbal(sp)
            delay = t_next - time.monotonic()
            if delay < -period:
                t_next = time.monotonic()  # fell behind: do not burst
            await asyncio.sleep(max(0.0, delay))

    async def _point_gimbal(self, sp: Setpoint) -> None:
        """Send the setpoint's camera pitch to the gimbal at <= 2 Hz when it moved by > 0.5 deg."""
        if sp.gimbal_pitch_rad is None:
            return
        now = time.monotonic()
        last = self._gimbal_sent
        if last is not None and (now - last[0] < 0.5 or abs(sp.gimbal_pitch_rad - last[1]) < math.radians(0.5)):
            return
        self._gimbal_sent = (now, sp.gimbal_pitch_rad)
        try:
            await self.autopilot.set_gimbal_pitch(sp.gimbal_pitch_rad)
        except Exception as e:
            log.warning("%s: gimbal command failed: %s", self.id, e)

    async def supervisor_loop(self) -> None:
        period = 0.1
        t_health = 0.0
        while True:
            await asyncio.sleep(period)
            self.supervise_once()
            now = time.monotonic()
            if self.tracking is not None and now - self._last_target_pub_s >= 1.0 / self.cfg.track.target_publish_hz - 1e-3:
                self._last_target_pub_s = now
                self.publish_target()
            if now - t_health >= 1.0 / self.cfg.rates.health_hz:
                t_health = now
                self.publish(keys.HEALTH, self.health())

    def supervise_once(self) -> None:
        T = self.autopilot.telemetry
        pos = T.get("pos")
        alt = -pos[2] if pos is not None else 0.0
        target_alt = getattr(self, "_takeoff_alt_m", self.cfg.flight.takeoff_altitude_m)
        before = self.mission.state
        # take-off done: at the asked altitude, or the autopilot finished its take-off elsewhere (PX4 may
        # use its own MIS_TAKEOFF_ALT) and holds still in the air
        settled = (T["flight_mode"] == "HOLD" and T["landed_state"] == "in_air" and alt > 1.0
                   and abs(T["vel"][2]) < 0.2)
        self.mission.vehicle(T["armed"], T["in_air"], alt >= 0.9 * target_alt or settled)
        if self.mission.state != before:
            log.info("%s: %s -> %s", self.id, before.value, self.mission.state.value)
            if self.mission.state == State.LANDED:
                self.source = None
        fs = self.cfg.safety
        self._check_offboard(T["flight_mode"])
        if self.mission.airborne:
            silent = time.monotonic() - self.t_last_gcs_s
            if silent > fs.gcs_heartbeat_timeout_s:
                self._failsafe(f"ground-station heartbeat lost for {silent:.1f} s", fs.gcs_loss_action)
            if T["battery_frac"] < fs.low_battery_frac:
                self._failsafe(f"low battery {100 * T['battery_frac']:.0f}%", fs.low_battery_action)
            self._check_separation(pos)

    def _check_offboard(self, mode: str) -> None:
        """Notice the autopilot leaving offboard under us (failsafe or pilot) and follow or resume."""
        ap = self.autopilot
        if not ap.offboard_active or mode == "OFFBOARD" or time.monotonic() - ap.offboard_since_s < 2.0:
            return
        now = time.monotonic()
        self._resumes = [t for t in self._resumes if now - t < 60.0]
        may_resume = len(self._resumes) < self.cfg.safety.offboard_resumes_per_min and self.source is not None \
            and self.rates["setpoint"].rate_hz() >= 0.5 * self.cfg.rates.setpoint_hz
        before = self.mission.state
        tr = self.mission.offboard_lost(mode, may_resume)
        reason = f"autopilot left offboard for {mode}"
        if tr.action == Action.RESUME_OFFBOARD:
            self._resumes.append(now)
            log.warning("%s: %s: switching back to offboard (%d in the last minute)", self.id, reason, len(self._resumes))
            self.warnings.append(reason + ", resumed")
            ap.offboard_since_s = now  # no second attempt before this one had time

            async def resume():
                try:
                    await ap.start_offboard()
                except Exception as e:
                    log.error("%s: resuming offboard failed: %s", self.id, e)

            self._spawn(resume(), "resume_offboard")
            return
        ap.offboard_active = False
        if self.mission.state != before or tr.state in (State.PAUSED, State.LANDING, State.RETURNING):
            log.warning("%s: %s: %s -> %s", self.id, reason, before.value, self.mission.state.value)
            self.warnings.append(reason)
            self.source = None

    def _check_separation(self, pos) -> None:
        plan = self.mission.plan
        if pos is None or self.mission.state != State.ORBIT:
            return
        near = closest_neighbour(pos, self.neighbours, time.monotonic())
        limit = plan.min_separation_m if plan is not None else 3.0
        if near is None or near[1] >= limit:
            self._separation_warned = False
            return
        reason = f"separation: {near[0]} at {near[1]:.1f} m (< {limit:.1f} m)"
        if self.cfg.safety.separation_action == "warn":
            if not self._separation_warned:
                log.warning("%s: %s", self.id, reason)
                self.warnings.append(reason)
            self._separation_warned = True
        else:
            self._failsafe(reason, self.cfg.safety.separation_action)

    def _failsafe(self, reason: str, action: str) -> None:
        tr = self.mission.trigger_failsafe(reason, action)
        if tr.action != Action.NONE:
            log.warning("%s: failsafe: %s -> %s", self.id, reason, action)
            self.warnings.append(reason)
            if self.failsafe_log is not None:
                self.failsafe_log.add(time.time(), action, [reason], source="mission")
            self._spawn(self._execute(tr.action, f"failsafe:{action}", {}), "failsafe")

    def health(self) -> Health:
        t, c = time.monotonic(), time.process_time()
        cpu = 100.0 * (c - self._cpu[1]) / max(t - self._cpu[0], 1e-6)
        self._cpu = (t, c)
        return Health(
            header=Health.make_header(self.id), role="agent", state=self.mission.state.value,
            ok=not self.warnings and self.autopilot.telemetry["health_ok"], warnings=self.warnings[-5:],
            cpu_percent=cpu, rates_hz={k: m.rate_hz() for k, m in self.rates.items()},
        )

    # --- life -----------------------------------------------------------------------------------------
    async def start(self) -> None:
        """Connect to the autopilot and the network; start the loops."""
        cfg = self.cfg
        loop = asyncio.get_running_loop()
        self._loop = loop
        from comms.transport import deliver_to_loop

        sub = lambda key, cb, t: self._subs.append(self.bus.subscribe(key, deliver_to_loop(loop, cb), t))
        sub(keys.gcs_key(cfg.fleet, keys.HEALTH), self.on_gcs_health, Health)
        sub(keys.gcs_key(cfg.fleet, keys.CMD), self.on_command, Command)
        sub(keys.gcs_key(cfg.fleet, keys.PLAN), self.on_plan, OrbitPlan)
        sub(keys.all_drones_key(cfg.fleet, keys.STATE), self.on_neighbour_state, VehicleState)
        if self.tracking is not None:
            sub(keys.all_drones_key(cfg.fleet, keys.DETECTIONS), self.on_detections, Detections)
            sub(keys.all_drones_key(cfg.fleet, keys.FORMATION_PLAN), self.on_formation_plan, FormationPlan)
            if not cfg.record_camera:
                topics = (keys.CAMERA_INFO, keys.SIM_DETECTIONS) + ((keys.CAMERA_IMAGE,) if self.detector_worker else ())
                for topic in topics:
                    sub(self.key(topic), self.on_camera, None)
        if cfg.record_camera:
            # the simulator camera also sends exact keypoints and simulated detections: kept for evaluation
            for topic in (keys.CAMERA_INFO, keys.CAMERA_IMAGE, keys.SIM_KEYPOINTS2D, keys.SIM_KEYPOINTS2D_GT,
                          keys.SIM_DETECTIONS):
                sub(self.key(topic), self.on_camera, None)
        try:
            self.bus.declare_alive(keys.alive_key(cfg.fleet, self.id))
        except Exception as e:
            log.warning("%s: no liveliness token: %s", self.id, e)
        await self.autopilot.connect(cfg.connection, cfg.connect_timeout_s)
        await self.autopilot.start_telemetry(cfg.rates.telemetry_hz)
        self._tasks.append(asyncio.create_task(self.control_loop(), name="control"))
        self._tasks.append(asyncio.create_task(self.supervisor_loop(), name="supervisor"))
        # a plan published before we started: ask for the latest one
        try:
            for rx in await asyncio.to_thread(self.bus.query_latest, keys.gcs_key(cfg.fleet, keys.PLAN), OrbitPlan, 0.5):
                self.on_plan(rx)
        except Exception as e:
            log.debug("%s: plan query failed: %s", self.id, e)
        log.info("%s: agent running (%s)", self.id, cfg.connection)

    async def shutdown(self) -> None:
        """SIGTERM: land (or hold) if airborne, as configured, then stop everything."""
        fs = self.cfg.safety
        if self.mission.airborne and self.mission.state not in (State.LANDING, State.RETURNING):
            log.warning("%s: shutdown while airborne: %s", self.id, fs.sigterm_action)
            tr = self.mission.trigger_failsafe("shutdown requested", fs.sigterm_action)
            if tr.action != Action.NONE:
                await self._execute(tr.action, "shutdown", {})
        if fs.sigterm_action == "land" and self.mission.airborne:
            t_end = time.monotonic() + fs.sigterm_land_timeout_s
            while self.mission.airborne and time.monotonic() < t_end:
                self.supervise_once()
                await asyncio.sleep(0.1)
            if self.mission.airborne:
                log.error("%s: still airborne after %.0f s of landing; exiting anyway", self.id, fs.sigterm_land_timeout_s)
        try:
            self.publish(keys.HEALTH, self.health())
        except Exception:
            pass
        for t in list(self._tasks):
            t.cancel()
        for t in list(self._tasks):
            try:
                await t
            except BaseException:
                pass
        for s in self._subs:
            try:
                s.close()
            except Exception:
                pass
        if self.detector_worker is not None:
            self.detector_worker.close(wait=False)
        await self.autopilot.close()

    async def run(self, stop: asyncio.Event) -> None:
        await self.start()
        await stop.wait()
        await self.shutdown()


async def run_agent(cfg: AgentConfig) -> int:
    """Process entry: open the transport and the recorder, run the agent until SIGTERM/SIGINT."""
    from onboard.agent.autopilot import MavsdkAutopilot
    from comms.transport import Transport

    cfg.validate()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    recorder = None
    if cfg.record.enabled:
        from flightdata.folder import Sortie
        from flightdata.recorder import Recorder
        from skycap.config import save_config

        # each start is a new sortie: a new file, so a restart never touches the last recording
        recorder = Recorder.new_sortie(cfg.record.dir, cfg.drone_id,
                                       metadata={"fleet": cfg.fleet, "connection": cfg.connection})
        save_config(cfg, Sortie.of(recorder.path).config_path)
    bus = Transport.open(cfg.transport, node_id=cfg.drone_id)
    origin = (cfg.origin.lat_deg, cfg.origin.lon_deg, cfg.origin.alt_m)
    agent = Agent(cfg, bus, MavsdkAutopilot(cfg.drone_id, origin=origin), recorder)
    try:
        await agent.run(stop)
    finally:
        if cfg.mode == "track" and recorder is not None:
            import json

            try:
                p = Sortie.of(recorder.path).track_stats_path  # this sortie's counters, beside its recording
                p.write_text(json.dumps(agent.tracking_stats()))
            except Exception as e:
                log.error("%s: writing the tracking statistics failed: %s", cfg.drone_id, e)
        if recorder is not None:
            recorder.close()
        bus.close()
    log.info("%s: agent stopped (pid %d)", cfg.drone_id, os.getpid())
    return 0
