"""The onboard agent's loop: one process per drone, on its companion computer.

It connects to its autopilot (:class:`onboard.agent.autopilot.MavsdkAutopilot`, MAVSDK as a companion
computer), joins the fleet over Zenoh (:class:`comms.transport.Transport`), takes plans and commands
from the ground station and answers each with a :class:`~shared_msgs.CommandAck`, flies its slot of the
orbit by streaming offboard setpoints, watches the ground-station heartbeat and the battery, and records
everything it sees to its MCAP file (:mod:`flightdata.recorder`).

The :class:`Agent` is the wiring; each part has one job and is testable alone:

* ``mission`` -- :class:`onboard.mission.Mission`, the pure state machine; validation in
  :func:`onboard.mission.validate_command` / :func:`~onboard.mission.validate_plan`.
* ``source`` -- the current :class:`onboard.setpoint.SetpointSource`, asked for one setpoint per control tick:
  an :class:`~onboard.orbit.OrbitController` (``mode = "orbit"``) or the formation MPC (``mode = "track"``,
  built by ``formation``), a :class:`~onboard.setpoint.HoldSource` while paused.
* ``perception`` -- a list of :class:`~onboard.agent.perception.PerceptionStage`; each camera frame goes
  through them in order and what they return is published and recorded.
* ``autopilot`` -- the thin MAVSDK adapter, its latest telemetry a typed record
  (:class:`onboard.agent.telemetry.Telemetry`); ``outbox`` -- keys, publishing on the Zenoh bus and recording
  (:class:`onboard.agent.outbox.Outbox`); ``teammates`` -- the other drones' states
  (:class:`onboard.agent.teammates.Teammates`); ``supervisor`` -- the vehicle's events into the mission, offboard
  loss and the ``safety`` failsafes: ground-station heartbeat, battery, separation
  (:class:`onboard.agent.supervisor.VehicleSupervisor`).
* track mode only (``mode = "track"``; None otherwise): ``tracking`` -- the tracking capture
  (:class:`onboard.agent.tracking.TrackingCapture`: own and teammates' detections -> the cooperative filter,
  the ONNX detector's worker); ``formation`` -- the formation setpoint source
  (:class:`onboard.agent.formation.FormationFlight`: the MPC around the fused person estimate);
  ``failsafes`` -- the formation failsafes (:class:`onboard.agent.failsafes.FormationFailsafes`, configured
  by ``track.failsafe``): re-space when a teammate falls silent or joins, brake and hold when a separation /
  geofence breach is predicted or the MPC keeps falling back, hold and turn to search when the person is lost,
  return / land on low battery (through the mission, like the ground-station-loss failsafe). Every change is
  logged, counted, kept in the health warnings and written to ``<drone>.track.json`` (``failsafe_events``,
  ``failsafe_counts``) with the malformed-detection and network-fault counters.

Loops (asyncio, one thread + MAVSDK's and Zenoh's own): the control loop (``rates.setpoint_hz``; under systemd it
also sends READY once the autopilot link is up and pings the watchdog: :meth:`Agent._systemd_tick`), the
supervisor (10 Hz: vehicle events, failsafes, health heartbeat) and the telemetry callbacks (50 Hz:
record state, publish it at ``rates.state_publish_hz``).

Gimbal: the setpoints' camera pitch is sent to the gimbal at <= 2 Hz in the background (a command waits for the
autopilot's ACK: never in the control loop's way); every gimbal report is published and recorded as
:class:`~shared_msgs.GimbalAttitude` on ``<drone>/gimbal``; ``gimbal_watch``
(:class:`onboard.agent.gimbal.GimbalWatch`) turns a gimbal that does not reach its command within 3 s into a
health warning.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import math
import time
from typing import TYPE_CHECKING, Any

import msgspec
import numpy as np

from comms.transport import deliver_to_loop
from onboard.agent.gimbal import GimbalWatch
from onboard.agent.outbox import Outbox
from onboard.agent.perception import PerceptionStage
from onboard.agent.rates import RateMeter
from onboard.agent.stats import tracking_stats
from onboard.agent.supervisor import VehicleSupervisor
from onboard.agent.teammates import Teammates
from onboard.config import AgentConfig
from onboard.mission import Action, Mission, State, validate_command, validate_plan
from onboard.orbit import OrbitController
from onboard.setpoint import HoldSource, Setpoint, SetpointSource
from onboard.zones import clamp_setpoint
from onboard.camera.pose import CameraPoser
from shared_msgs import (
    CameraFrame,
    CameraInfo,
    CameraStatus,
    Command,
    CommandAck,
    Detections,
    DetectorStatus,
    FormationPlan,
    GimbalAttitude,
    Health,
    Keypoints2D,
    OrbitPlan,
    VehicleState,
    encode,
    keys,
    stamp_sent,
)
from skycap.frames import yaw_from_quat_wxyz
from skycap.sdnotify import Notifier

if TYPE_CHECKING:  # annotations only: the track-mode parts are imported when track mode is configured
    from onboard.agent.failsafes import FormationFailsafes
    from onboard.agent.formation import FormationFlight
    from onboard.agent.tracking import TrackingCapture

log = logging.getLogger(__name__)

__all__ = ["Agent"]


class Agent:
    """One drone's agent. ``await agent.run(stop)`` until ``stop`` is set (SIGTERM), then shut down cleanly."""

    def __init__(self, cfg: AgentConfig, bus: Any, autopilot: Any, recorder: Any = None,
                 perception: list[PerceptionStage] | None = None, notifier: Notifier | None = None):
        self.cfg = cfg.validate()
        #: systemd's notify protocol (the process entry passes one from the environment; a no-op otherwise)
        self.notifier = notifier if notifier is not None else Notifier.disabled()
        self._t_first_state_s: float | None = None  #: monotonic time of the first vehicle state
        self.link_up = False  #: the autopilot link is up: first telemetry with the landed state, restart policy applied
        self.id = cfg.drone_id
        self.bus = bus
        self.autopilot = autopilot
        self.outbox = Outbox(cfg.fleet, cfg.drone_id, bus, recorder)
        if cfg.record.enabled:
            self.outbox.record_dir = cfg.record.dir  # its free space is reported (health) even with no recording open
        else:
            self.outbox.no_recorder_reason = "recording disabled in the agent's configuration (record.enabled = false)"
        self.perception: list[PerceptionStage] = list(perception or [])
        self.mission = Mission()
        self.teammates = Teammates(cfg.drone_id)
        self.source: SetpointSource | None = None
        self.last_setpoint: Setpoint | None = None
        self.state: VehicleState | None = None
        self.camera_info: CameraInfo | None = None
        self.rates = {k: RateMeter() for k in ("setpoint", "state", "frame", "keypoints")}
        self.warnings: list[str] = []
        self._camera_connected = True  #: the camera service's last CameraStatus said so (a loss warns once)
        #: a real camera's frames come without a pose: stamped from the reported states and gimbal attitude
        self.camera_poser: CameraPoser | None = None
        if cfg.camera.source != "sim":
            self.camera_poser = CameraPoser(cfg.camera.mount, math.radians(cfg.camera.pitch_deg),
                                            cfg.camera.lever_arm_body_m)
        self.acks: list[CommandAck] = []  # for tests and the health report
        self._act_lock = asyncio.Lock()
        self._tasks: list[asyncio.Task] = []
        self._subs: list[Any] = []
        self._last_state_pub_s = 0.0
        self._cpu = (time.monotonic(), time.process_time())
        self._gimbal_sent: tuple[float, float] | None = None
        self._t_release_s = -math.inf
        #: monotonic times of the setpoints sent in the last few seconds (stall detection)
        self._sp_times: collections.deque[float] = collections.deque(maxlen=400)
        self._gimbal_task: asyncio.Task | None = None
        self.gimbal_watch = GimbalWatch()
        self.zone_clamps = 0  #: setpoints moved out of a keep-out zone / into the fence (:meth:`keep_in_zones`)
        self._zone_warned: set[tuple[str, str]] = set()  #: (plan id, zone) already warned about
        self.supervisor = VehicleSupervisor(cfg, self.mission, autopilot, self.teammates, failsafe=self._failsafe,
                                            stop_setpoints=self._stop_setpoints, resume_offboard=self._resume_offboard,
                                            setpoints_flowing=self._setpoints_flowing, warn=self.warnings.append,
                                            setpoint_gap_s=self._setpoint_gap_s)
        #: track mode's parts (None in orbit mode)
        self.tracking: TrackingCapture | None = None
        self.failsafes: FormationFailsafes | None = None
        self.formation: FormationFlight | None = None
        if cfg.mode == "track":
            # the track-mode parts pull the filter (scipy), the MPC (casadi): imported only when configured,
            # so that an orbit-mode agent starts fast
            from onboard.agent.failsafes import FormationFailsafes
            from onboard.agent.formation import FormationFlight
            from onboard.agent.tracking import TrackingCapture

            self.failsafes = FormationFailsafes(self.id, cfg.track.failsafe, self._failsafe, self.warnings.append)
            self.tracking = TrackingCapture(self.id, cfg.track, self.outbox.publish, self.failsafes.log,
                                            self.warnings.append)
            self.rates["detections"] = self.tracking.detections_rate
            self.formation = FormationFlight(cfg, tracking=self.tracking, failsafes=self.failsafes,
                                             teammates=self.teammates, autopilot=autopilot, mission=self.mission,
                                             publish=self.outbox.publish)
        autopilot.on_state = self._on_state
        autopilot.on_gimbal = self._on_gimbal

    def ack(self, command_id: str, result: str, reason: str = "") -> None:
        a = CommandAck(header=CommandAck.make_header(self.id), command_id=command_id, result=result, reason=reason)
        self.acks.append(a)
        (log.warning if result in ("refused", "failed") else log.info)(
            "%s: %s %s%s", self.id, result, command_id, f": {reason}" if reason else "")
        self.outbox.publish(keys.ACK, a)

    # --- inputs (run on the loop) -------------------------------------------------------------------
    def _on_state(self, st: VehicleState) -> None:
        self.state = st
        if self.camera_poser is not None:
            self.camera_poser.add_state(st)
        self.rates["state"].tick()
        if self.tracking is not None:
            self.tracking.on_state(st)
        if self.outbox.recorder is not None:
            self.outbox.record(self.outbox.key(keys.STATE), encode(stamp_sent(st)), st.header.t_measurement_ns)
        t = time.monotonic()
        if t - self._last_state_pub_s >= 1.0 / self.cfg.rates.state_publish_hz - 1e-3:
            self._last_state_pub_s = t
            try:
                self.bus.publish(self.outbox.key(keys.STATE), st)
            except Exception as e:
                log.debug("state publish failed: %s", e)

    def _on_gimbal(self, msg: GimbalAttitude) -> None:
        """A gimbal report: published and recorded (the gimbal's rate), and checked against the last command."""
        self.rates.setdefault("gimbal", RateMeter()).tick()
        if self.camera_poser is not None:
            self.camera_poser.add_gimbal(msg)
        self.gimbal_watch.report(time.monotonic(), msg.pitch_rad, msg.yaw_rad)
        self.outbox.publish(keys.GIMBAL, msg)

    def on_gcs_health(self, rx) -> None:
        self.supervisor.on_gcs_heartbeat()

    def on_neighbour_state(self, rx) -> None:
        self.teammates.note(keys.parse_key(rx.key)[1], rx.msg, time.monotonic(), time.time())

    def on_detections(self, rx) -> None:
        """A teammate's shared detections (track mode): fused into this drone's filter."""
        if self.tracking is None or not isinstance(rx.msg, Detections):
            return
        if keys.parse_key(rx.key)[1] == self.id:
            return  # our own, already fused
        self.outbox.record(rx.key, rx.data, rx.t_received_ns)
        self.tracking.teammate_detections(rx.msg)

    def on_formation_plan(self, rx) -> None:
        """A teammate's shared MPC plan (track mode): avoided by this drone's MPC."""
        if self.formation is None or not isinstance(rx.msg, FormationPlan):
            return
        self.formation.on_teammate_plan(keys.parse_key(rx.key)[1], rx.msg, self.source)

    def _sender(self, rx) -> str:
        """Who sent ``rx``, for the log: the sender id, authenticated by its certificate when the transport is
        secure (the ACL lets only that certificate publish under its keys; the transport refused any other
        claimed sender id)."""
        who = rx.msg.header.sender_id
        if self.bus.secure:
            return f"{who!r} (authenticated: certificate CN {who!r}, mutual TLS + fleet ACL)"
        return f"{who!r} (NOT authenticated: insecure transport)"

    def on_command(self, rx) -> None:
        self.outbox.record(rx.key, rx.data, rx.t_received_ns)
        cmd: Command = rx.msg
        if cmd.target not in ("*", self.id):
            return  # another drone's command: its agent answers
        log.info("%s: command %s %s for %s from %s", self.id, cmd.action, cmd.command_id, cmd.target,
                 self._sender(rx))
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
        self.outbox.record(rx.key, rx.data, rx.t_received_ns)
        plan: OrbitPlan = rx.msg
        if self.mission.plan is not None and plan.plan_id == self.mission.plan.plan_id and \
                plan.header.t_sent_ns == self.mission.plan.header.t_sent_ns:
            return  # the same plan again (live + query)
        log.info("%s: orbit plan %s from %s", self.id, plan.plan_id, self._sender(rx))
        reason = validate_plan(plan, self.id, self.cfg.safety, rx.t_received_ns, mode=self.cfg.mode)
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
            self.outbox.record(rx.key, rx.data, rx.t_received_ns)
        if isinstance(msg, CameraInfo):
            self.camera_info = msg
            if self.tracking is not None:
                self.tracking.set_camera_info(msg)
        elif isinstance(msg, Detections):
            if self.tracking is not None and rx.key == self.outbox.key(keys.SIM_DETECTIONS):
                self.tracking.on_sim_detections(msg)
        elif isinstance(msg, CameraFrame):
            self.rates["frame"].tick()
            if len(msg.T_world_cam) != 16 and self.camera_poser is not None:
                T = self.camera_poser.T_world_cam(msg.header.t_measurement_ns)
                if T is not None:  # None: no state near the capture time; the tracking skips such a frame
                    msg = msgspec.structs.replace(msg, T_world_cam=tuple(float(v) for v in T.ravel()))
            if self.tracking is not None:
                self.tracking.on_frame(msg)
            for stage in self.perception:
                try:
                    for topic, out in stage.process(msg, self.camera_info, self.state):
                        self.outbox.publish(topic, out)
                except Exception:
                    log.exception("%s: perception stage %s failed", self.id, stage.name)
        elif isinstance(msg, Keypoints2D):
            self.rates["keypoints"].tick()
        elif isinstance(msg, CameraStatus):
            if not msg.connected and self._camera_connected:
                reason = f"camera {msg.camera_id} ({msg.source}) lost: {msg.detail or 'no frames'}"
                log.warning("%s: %s", self.id, reason)
                self.warnings.append(reason)
            elif msg.connected and not self._camera_connected:
                log.info("%s: camera %s (%s) delivering frames", self.id, msg.camera_id, msg.source)
            self._camera_connected = msg.connected

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
                    if not ap.telemetry.armed:
                        await ap.arm()
                    self.supervisor.takeoff_alt_m = float(params.get("altitude_m", self.cfg.flight.takeoff_altitude_m))
                    self.supervisor.takeoff_confirmed = False
                    await ap.takeoff(self.supervisor.takeoff_alt_m)
                    self.supervisor.takeoff_confirmed = True
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
                    self.mission.state = State.IDLE if not ap.telemetry.armed else State.ARMED
                return
            self.ack(command_id, "completed")

    async def source_for(self, plan: OrbitPlan) -> SetpointSource:
        """The setpoint source that flies ``plan``, by ``cfg.mode``: the orbit controller ("orbit"), the formation
        MPC ("track"; its solver is built off the event loop)."""
        if self.formation is not None:
            return await asyncio.to_thread(self.formation.build_source, plan)
        fl = self.cfg.flight
        return OrbitController(plan, self.id, fl.approach_speed_m_s, fl.approach_climb_m_s,
                               trim_gain_per_s=fl.orbit_trim_gain_per_s, trim_max_m=fl.orbit_trim_max_m)

    async def _start_orbit(self) -> None:
        plan = self.mission.plan
        st = self.state
        if plan is None or st is None:
            raise RuntimeError("no plan or no vehicle state yet")
        # a start during the take-off: PX4 ends its take-off with HOLD, which would override an offboard switch
        # made at that moment: wait until the take-off is over
        t_end = time.monotonic() + 60.0
        while self.mission.state == State.ORBIT and not self.autopilot.offboard_active and (
                self.autopilot.telemetry.flight_mode == "TAKEOFF" or self.autopilot.telemetry.landed_state == "taking_off"):
            if time.monotonic() > t_end:
                raise RuntimeError("the autopilot is still in its take-off after 60 s")
            await asyncio.sleep(0.1)
        self.source = await self.source_for(plan)
        if not self.autopilot.offboard_active:
            # PX4 refuses offboard without a setpoint stream: let the control loop stream first.
            await asyncio.sleep(max(1.0, 10.0 / self.cfg.rates.setpoint_hz))
            await self.autopilot.start_offboard()

    # --- statistics -----------------------------------------------------------------------------------
    def tracking_stats(self) -> dict:
        """What the flight summary needs from this agent's tracking (written next to its recording)."""
        return tracking_stats(self.cfg, self._subs, self.tracking, self.formation, self.failsafes)

    # --- loops ----------------------------------------------------------------------------------------
    def next_setpoint(self, src: SetpointSource, t_s: float, st: VehicleState) -> Setpoint:
        """One control step of ``src``: through the formation (track mode: estimate, failsafes, MPC, shared
        plan), or the source alone (orbit mode); then kept out of the plan's keep-out zones and inside its fence
        (:meth:`keep_in_zones`)."""
        if self.formation is not None:
            sp = self.formation.step(src, t_s, st)
        else:
            sp = src.update(t_s, np.asarray(st.position_ned_m), np.asarray(st.velocity_ned_m_s),
                            yaw_from_quat_wxyz(st.q_world_body))
        return self.keep_in_zones(sp)

    def keep_in_zones(self, sp: Setpoint) -> Setpoint:
        """The plan's geofence and keep-out zones on the setpoint (:func:`onboard.zones.clamp_setpoint`): a setpoint
        in a zone or outside the fence is moved to its edge; each zone that clamps warns once per plan (health
        warning, log) and every clamped setpoint is counted (``zone_clamps``)."""
        plan = self.mission.plan
        if plan is None or (plan.geofence is None and not plan.keepout_zones):
            return sp
        p, v, what = clamp_setpoint(sp.position_ned_m, sp.velocity_ned_m_s, plan.geofence, plan.keepout_zones)
        if not what:
            return sp
        self.zone_clamps += 1
        for w in what:
            key = (plan.plan_id, w)
            if key not in self._zone_warned:
                self._zone_warned.add(key)
                text = f"setpoint clamped: it would have entered {w}" if w.startswith("keep-out") else \
                    f"setpoint clamped: it would have left the {w}"
                log.warning("%s: %s (plan %s)", self.id, text, plan.plan_id)
                self.warnings.append(text)
        return Setpoint(p, v, sp.yaw_rad, sp.gimbal_pitch_rad, np.zeros(3))

    async def control_loop(self) -> None:
        period = 1.0 / self.cfg.rates.setpoint_hz
        t_next = time.monotonic()
        while True:
            t_next += period
            self._systemd_tick()
            src, st = self.source, self.state
            if src is not None and st is not None:
                try:
                    sp = self.next_setpoint(src, time.time(), st)
                    await self.autopilot.set_setpoint(sp)
                    self.last_setpoint = sp
                    self.rates["setpoint"].tick()
                    self._sp_times.append(time.monotonic())
                except Exception as e:
                    log.warning("%s: setpoint failed: %s", self.id, e)
                else:
                    await self._point_gimbal(sp)
            delay = t_next - time.monotonic()
            if delay < -period:
                t_next = time.monotonic()  # fell behind: do not burst
            await asyncio.sleep(max(0.0, delay))

    def _systemd_tick(self) -> None:
        """Each control tick: READY once the autopilot link is up (:meth:`_check_link_up`; the recorder opened
        before the agent was made), the mission state as the service status, and the watchdog ping: sent from the
        control loop itself, so that a stuck loop (an await that never returns, a blocked event loop) stops the
        pings and systemd restarts the agent (``WatchdogSec=``, deploy/INSTALL.md)."""
        n = self.notifier
        if not self.link_up and self._check_link_up():
            self.link_up = True
            n.ready(f"{self.id}: ready, {self.mission.state.value}")
        elif self.link_up:
            n.status(f"{self.id}: {self.mission.state.value}" + (f" (failsafe: {self.mission.failsafe})"
                                                                 if self.mission.failsafe else ""))
        n.watchdog()

    def _check_link_up(self) -> bool:
        """The autopilot link is up: a vehicle state arrived and the autopilot reported its landed state (or 3 s
        passed without one). A vehicle already in the air then (the agent restarted in flight) is taken over by
        ``safety.on_restart_airborne``: "resume" (hover under the agent: the airborne failsafes run again and the
        ground station's start resumes the orbit) or "land"."""
        if self.state is None:
            self.notifier.status(f"{self.id}: autopilot connected, waiting for the first telemetry")
            return False
        now = time.monotonic()
        if self._t_first_state_s is None:
            self._t_first_state_s = now
        T = self.autopilot.telemetry
        if T.landed_state == "unknown" and now - self._t_first_state_s < 3.0:
            self.notifier.status(f"{self.id}: waiting for the autopilot's landed state")
            return False
        if self.mission.state == State.IDLE and (T.in_air or T.landed_state in ("in_air", "taking_off", "landing")):
            policy = self.cfg.safety.on_restart_airborne
            reason = (f"started with the vehicle airborne ({T.landed_state}, {T.altitude_m:.1f} m, "
                      f"{T.flight_mode}): safety.on_restart_airborne = {policy}")
            log.warning("%s: %s", self.id, reason)
            self.warnings.append(reason)
            self.mission.state = State.HOVER  # adopted: the vehicle is flying and now the agent's again
            if policy == "land":
                self._failsafe("agent restarted with the vehicle airborne", "land")
        return True

    async def _point_gimbal(self, sp: Setpoint) -> None:
        """Send the setpoint's camera pitch to the gimbal at <= 2 Hz when it moved by > 0.5 deg, in the
        background (one command in flight at a time)."""
        if sp.gimbal_pitch_rad is None or (self._gimbal_task is not None and not self._gimbal_task.done()):
            return
        now = time.monotonic()
        last = self._gimbal_sent
        if last is not None and (now - last[0] < 0.5 or abs(sp.gimbal_pitch_rad - last[1]) < math.radians(0.5)):
            return
        self._gimbal_sent = (now, sp.gimbal_pitch_rad)
        self._gimbal_task = asyncio.get_running_loop().create_task(self._send_gimbal(sp.gimbal_pitch_rad),
                                                                   name="gimbal")

    async def _send_gimbal(self, pitch_rad: float) -> None:
        t = time.monotonic()
        try:
            if await self.autopilot.set_gimbal_pitch(pitch_rad):
                self.gimbal_watch.command(t, pitch_rad, 0.0)
            else:
                self._gimbal_sent = (t, math.nan)  # no gimbal yet: ask again in 0.5 s even if the pitch is the same
        except Exception as e:
            log.warning("%s: gimbal command failed: %s", self.id, e)

    def _check_gimbal(self, now: float) -> None:
        w = self.gimbal_watch.check(now)
        if w is not None:
            log.warning("%s: %s", self.id, w)
            self.warnings.append(w)

    async def supervisor_loop(self) -> None:
        period = 0.1
        t_health = 0.0
        while True:
            await asyncio.sleep(period)
            self.supervise_once()
            now = time.monotonic()
            self._check_gimbal(now)
            self._release_offboard(now)
            if self.tracking is not None:
                self.tracking.publish_target(now)
            if now - t_health >= 1.0 / self.cfg.rates.health_hz:
                t_health = now
                self.outbox.publish(keys.HEALTH, self.health())

    def _release_offboard(self, now: float) -> None:
        """A vehicle landed (or found at connect) disarmed in OFFBOARD is put in HOLD (every 5 s at most) so that it
        reports armable again: the operator's pre-flight checks and the next take-off need it."""
        ap = self.autopilot
        if not ap.landed_in_offboard() or now - self._t_release_s < 5.0:
            return
        self._t_release_s = now

        async def release():
            try:
                await ap.release_offboard()
            except Exception as e:
                log.warning("%s: %s", self.id, e)

        self._spawn(release(), "release_offboard")

    def supervise_once(self) -> None:
        """Vehicle events into the mission, offboard loss, the ``safety`` failsafes (:class:`VehicleSupervisor`)."""
        self.supervisor.check()

    def _setpoints_flowing(self) -> bool:
        """A setpoint source is set and the stream went out at >= half its rate lately."""
        return self.source is not None and self.rates["setpoint"].rate_hz() >= 0.5 * self.cfg.rates.setpoint_hz

    def _stop_setpoints(self) -> None:
        self.source = None

    def _setpoint_gap_s(self, window_s: float = 5.0) -> float:
        """The longest gap (s) between two setpoints sent, or since the last one, among the gaps that end in the
        last ``window_s``; 0 before the first setpoint."""
        now = time.monotonic()
        ts = [*self._sp_times, now]
        return max((b - a for a, b in zip(ts, ts[1:]) if now - b <= window_s), default=0.0)

    def _resume_offboard(self) -> None:
        ap = self.autopilot

        async def resume():
            try:
                # fly back from wherever the autopilot took the vehicle (its Return climbs): a fresh source
                # approaches the slot from the current position instead of jumping to it
                if (self.formation is None and self.mission.state == State.ORBIT and self.mission.plan is not None
                        and self.source is not None):
                    self.source = await self.source_for(self.mission.plan)
                await ap.start_offboard()
            except Exception as e:
                log.error("%s: resuming offboard failed: %s", self.id, e)

        self._spawn(resume(), "resume_offboard")

    def _failsafe(self, reason: str, action: str) -> None:
        tr = self.mission.trigger_failsafe(reason, action)
        if tr.action != Action.NONE:
            log.warning("%s: failsafe: %s -> %s", self.id, reason, action)
            self.warnings.append(reason)
            if self.failsafes is not None:
                self.failsafes.log.add(time.time(), action, [reason], source="mission")
            self._spawn(self._execute(tr.action, f"failsafe:{action}", {}), "failsafe")

    def health(self) -> Health:
        t, c = time.monotonic(), time.process_time()
        cpu = 100.0 * (c - self._cpu[1]) / max(t - self._cpu[0], 1e-6)
        self._cpu = (t, c)
        return Health(
            header=Health.make_header(self.id), role="agent", state=self.mission.state.value,
            ok=not self.warnings and self.autopilot.telemetry.health_ok, warnings=self.warnings[-5:],
            cpu_percent=cpu, rates_hz={k: m.rate_hz() for k, m in self.rates.items()},
            recorder=self.outbox.recorder_status(), detector=self.detector_status(),
        )

    def detector_status(self) -> DetectorStatus:
        """The onboard detector as the health reports it: an ONNX model is loaded (its session opened when the
        agent was built: a model that does not load stops the agent there) only with ``track.detections = "onnx"``;
        otherwise this drone needs none, and ``model`` says why."""
        if self.tracking is None:
            if self.cfg.camera.source == "sim":
                why = "none (orbit mode: simulated keypoints)"
            else:
                why = f"none (orbit mode: {self.cfg.camera.source} camera frames recorded, no onboard detection)"
            return DetectorStatus(required=False, loaded=False, model=why)
        w = self.tracking.detector_worker
        rate = self.tracking.detections_rate.rate_hz()
        if w is None:
            return DetectorStatus(required=False, loaded=False, model="none (track mode: the simulator's detections)",
                                  rate_hz=rate)
        closed = getattr(w, "_closed", False)
        failed = int(w.counts.get("failed", 0))
        error = "the detector's worker is closed" if closed else (f"{failed} frames failed" if failed else "")
        return DetectorStatus(required=True, loaded=not closed and getattr(w.detector, "session", None) is not None,
                              model=str(getattr(w.detector, "name", self.cfg.track.detector_model)), rate_hz=rate,
                              error=error)

    # --- life -----------------------------------------------------------------------------------------
    async def start(self) -> None:
        """Connect to the autopilot and the network; start the loops."""
        cfg = self.cfg
        loop = asyncio.get_running_loop()
        if self.tracking is not None:
            self.tracking.attach(loop)

        def sub(key: str, cb, msg_type) -> None:
            self._subs.append(self.bus.subscribe(key, deliver_to_loop(loop, cb), msg_type))

        sub(keys.gcs_key(cfg.fleet, keys.HEALTH), self.on_gcs_health, Health)
        sub(keys.gcs_key(cfg.fleet, keys.CMD), self.on_command, Command)
        sub(keys.gcs_key(cfg.fleet, keys.PLAN), self.on_plan, OrbitPlan)
        sub(keys.all_drones_key(cfg.fleet, keys.STATE), self.on_neighbour_state, VehicleState)
        if self.tracking is not None:
            sub(keys.all_drones_key(cfg.fleet, keys.DETECTIONS), self.on_detections, Detections)
            sub(keys.all_drones_key(cfg.fleet, keys.FORMATION_PLAN), self.on_formation_plan, FormationPlan)
            if not cfg.record_camera:
                onnx = self.tracking.detector_worker is not None
                topics = (keys.CAMERA_INFO, keys.SIM_DETECTIONS) + ((keys.CAMERA_IMAGE,) if onnx else ())
                for topic in topics:
                    sub(self.outbox.key(topic), self.on_camera, None)
        if cfg.record_camera:
            # the simulator camera also sends exact keypoints and simulated detections: kept for evaluation
            for topic in (keys.CAMERA_INFO, keys.CAMERA_IMAGE, keys.CAMERA_STATUS, keys.SIM_KEYPOINTS2D,
                          keys.SIM_KEYPOINTS2D_GT, keys.SIM_DETECTIONS):
                sub(self.outbox.key(topic), self.on_camera, None)
        try:
            self.bus.declare_alive(keys.alive_key(cfg.fleet, self.id))
        except Exception as e:
            log.warning("%s: no liveliness token: %s", self.id, e)
        self.notifier.status(f"{self.id}: connecting to the autopilot on {cfg.connection}")
        await self.autopilot.connect(cfg.connection, cfg.connect_timeout_s)
        await self.autopilot.start_telemetry(cfg.rates.telemetry_hz)
        self.autopilot.mode_confirm_timeout_s = cfg.autopilot.mode_confirm_timeout_s
        self.notifier.status(f"{self.id}: autopilot connected, checking its parameters")
        await self.autopilot.apply_params(cfg.autopilot.params(cfg.flight.takeoff_altitude_m), write=cfg.autopilot.set_params)
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
            self.outbox.publish(keys.HEALTH, self.health())
        except Exception:
            pass
        if self._gimbal_task is not None:
            self._tasks.append(self._gimbal_task)
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
        if self.tracking is not None:
            self.tracking.close()
        await self.autopilot.close()

    async def run(self, stop: asyncio.Event) -> None:
        await self.start()
        await stop.wait()
        self.notifier.stopping(f"{self.id}: stopping" + (f", {self.cfg.safety.sigterm_action} first"
                                                         if self.mission.airborne else ""))
        await self.shutdown()
