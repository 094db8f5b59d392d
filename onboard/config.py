"""Typed configuration of the onboard agent (``skycap agent``), loaded from TOML with ``--config``/``--set``.

See ``deploy/agent.example.toml`` for a commented example.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from comms.transport import TransportConfig
from onboard.camera.config import CameraConfig
from skycap.config import ConfigError

__all__ = ["AgentConfig", "AutopilotConfig", "TrackConfig", "FormationFailsafeConfig", "OriginConfig", "SafetyConfig", "RatesConfig", "FlightConfig", "RecordConfig"]


@dataclass
class RatesConfig:
    """Loop and stream rates (Hz)."""

    #: offboard setpoint stream (PX4 needs >= 2 Hz; the issue asks >= 10)
    setpoint_hz: float = 20.0
    #: MAVSDK telemetry rate asked of the autopilot for position_velocity_ned and attitude (recorded)
    telemetry_hz: float = 50.0
    #: VehicleState on Zenoh (the recorder keeps every sample)
    state_publish_hz: float = 10.0
    #: agent Health heartbeat on Zenoh
    health_hz: float = 2.0


@dataclass
class SafetyConfig:
    """Failsafes of the agent (on top of the autopilot's own)."""

    #: land (or ``gcs_loss_action``) when no ground-station heartbeat arrived for this long while airborne
    gcs_heartbeat_timeout_s: float = 5.0
    #: "land", "return" or "hold"
    gcs_loss_action: str = "land"
    #: land below this battery fraction (0..1)
    low_battery_frac: float = 0.2
    low_battery_action: str = "land"
    #: on SIGTERM while airborne: "land" (and wait for touchdown up to ``sigterm_land_timeout_s``) or "hold"
    sigterm_action: str = "land"
    sigterm_land_timeout_s: float = 20.0
    #: the agent (re)started and found the vehicle already in the air (systemd restarted it after a crash or a
    #: watchdog timeout; the autopilot's offboard-loss failsafe holds the vehicle meanwhile): "land" it, or
    #: "resume" (take it over hovering: the airborne failsafes run again, the ground station's start resumes the
    #: orbit)
    on_restart_airborne: str = "land"
    #: another drone closer than the plan's min_separation_m while airborne: "hold", "land" or "warn"
    separation_action: str = "hold"
    #: when the autopilot leaves offboard after a stall of the setpoint stream (its offboard-loss Hold / Return;
    #: see ``autopilot.on_failsafe``), switch back this many times per minute
    #: at most (0: never; then the drone pauses until the operator sends start again)
    offboard_resumes_per_min: int = 3
    #: plan altitude band (metres above ground)
    min_altitude_m: float = 2.0
    max_altitude_m: float = 60.0
    max_radius_m: float = 200.0
    #: refuse plans whose slot speed radius*omega exceeds this
    max_speed_m_s: float = 8.0


@dataclass
class FlightConfig:
    """How the agent flies."""

    takeoff_altitude_m: float = 3.0
    #: carrot speed towards the orbit slot (horizontal / vertical)
    approach_speed_m_s: float = 3.0
    approach_climb_m_s: float = 1.5
    #: orbit trim: the integral gain (1/s) of the tracking error in the orbit's rotating frame added to the
    #: streamed position once on the slot (0 = off; see :class:`onboard.orbit.OrbitController`), and its bound (m)
    orbit_trim_gain_per_s: float = 0.3
    orbit_trim_max_m: float = 1.5
    #: how long to wait for the autopilot's health checks before refusing to arm
    health_timeout_s: float = 30.0


#: PX4's values of the failsafe-action parameters the agent sets (COM_OBL_RC_ACT / NAV_RCL_ACT)
OFFBOARD_LOSS_ACTIONS = {"return": 3, "land": 4, "hold": 5}
RC_LOSS_ACTIONS = {"hold": 1, "return": 2, "land": 3}


@dataclass
class AutopilotConfig:
    """What the agent expects of its autopilot (PX4 or the built-in simulator), set or checked at connect.

    With ``set_params`` the agent writes these PX4 parameters at connect and logs every value it changed (with
    ``false`` it only reads them and warns where they differ). A parameter the autopilot does not have is
    reported once and skipped. ``on_failsafe`` is the agent's policy when the autopilot takes the vehicle out
    of offboard itself (its offboard-loss failsafe after a stall of the agent, or its own Return / Hold):
    "resume" = report it and switch back to offboard as soon as the setpoints flow again (at most
    ``safety.offboard_resumes_per_min`` times a minute; an autopilot LAND is always followed), "follow" =
    report it and leave the vehicle to the autopilot's action (Return / Land followed, Hold = paused).
    """

    set_params: bool = True
    #: COM_OF_LOSS_T: seconds without setpoints before the autopilot's offboard-loss failsafe
    offboard_loss_timeout_s: float = 1.0
    #: COM_OBL_RC_ACT: the autopilot's reaction to offboard loss: "hold", "land" or "return" (PX4's default with
    #: no RC link is Return, which climbs to its RTL altitude above a fleet)
    offboard_loss_action: str = "hold"
    #: NAV_RCL_ACT: the reaction to a lost RC link (a safety pilot's radio): "hold", "return" or "land"
    rc_loss_action: str = "return"
    #: RTL_RETURN_ALT and RTL_DESCEND_ALT: Return mode's altitude above home (m; PX4 defaults 60 / 30)
    rtl_return_alt_m: float = 15.0
    #: "resume" or "follow" (see above)
    on_failsafe: str = "resume"
    #: seconds the agent waits for a commanded mode to show in the autopilot's reported mode (PX4 reports its
    #: mode in its 1 Hz heartbeat), once re-sent, before calling the command failed
    mode_confirm_timeout_s: float = 3.0
    #: after the autopilot took over (``on_failsafe = "resume"``): seconds to wait for the setpoint stream to
    #: flow again before following the autopilot's action instead
    resume_wait_s: float = 3.0

    def params(self, takeoff_altitude_m: float) -> dict[str, float | int]:
        """The PX4 parameters the agent relies on: name -> value (ints for PX4's INT32 parameters)."""
        return {
            "COM_OF_LOSS_T": float(self.offboard_loss_timeout_s),
            "COM_OBL_RC_ACT": OFFBOARD_LOSS_ACTIONS[self.offboard_loss_action],
            "NAV_RCL_ACT": RC_LOSS_ACTIONS[self.rc_loss_action],
            "MIS_TAKEOFF_ALT": float(takeoff_altitude_m),
            "RTL_RETURN_ALT": float(self.rtl_return_alt_m),
            "RTL_DESCEND_ALT": float(self.rtl_return_alt_m),
        }

    def validate(self) -> None:
        if self.offboard_loss_action not in OFFBOARD_LOSS_ACTIONS:
            raise ConfigError(f"autopilot.offboard_loss_action={self.offboard_loss_action!r}; use "
                              f"{' / '.join(OFFBOARD_LOSS_ACTIONS)}")
        if self.rc_loss_action not in RC_LOSS_ACTIONS:
            raise ConfigError(f"autopilot.rc_loss_action={self.rc_loss_action!r}; use {' / '.join(RC_LOSS_ACTIONS)}")
        if self.on_failsafe not in ("resume", "follow"):
            raise ConfigError(f"autopilot.on_failsafe={self.on_failsafe!r}; use 'resume' or 'follow'")
        if not 0.2 <= self.offboard_loss_timeout_s <= 10.0:
            raise ConfigError(f"autopilot.offboard_loss_timeout_s={self.offboard_loss_timeout_s}: use 0.2..10 s")
        if not 5.0 <= self.rtl_return_alt_m <= 120.0:
            raise ConfigError(f"autopilot.rtl_return_alt_m={self.rtl_return_alt_m}: use 5..120 m above home")
        if self.mode_confirm_timeout_s <= 0 or self.resume_wait_s < 0:
            raise ConfigError("autopilot.mode_confirm_timeout_s must be > 0 and resume_wait_s >= 0")


@dataclass
class RecordConfig:
    """Flight recording (MCAP, one file per drone)."""

    enabled: bool = True
    #: folder of the flight; the agent writes ``<dir>/<drone_id>.mcap``
    dir: str = "flights/latest"
    #: longest time between the recorder's fsyncs: the most of the recording an agent crash (kill -9, power
    #: loss) loses at the end of its file (the fault suite's budget is 1 s per crash, restart included)
    flush_interval_s: float = 0.25
    #: when the recorder fails (its writer died, an I/O error), open a new recording (the next sortie file) at
    #: most this often (s); a failure to open one (disk full) is retried as often
    reopen_interval_s: float = 5.0
    #: fault injection (simulation and fault tests only, off on real drones): SIGUSR1 kills the recorder's
    #: writer thread, SIGUSR2 makes the recording folder's disk "full" (flightdata.recorder.simulate_disk_full)
    fault_signals: bool = False


@dataclass
class OriginConfig:
    """Geodetic origin of the flight's world NED frame (WGS-84): it fixes the *horizontal* frame only.

    North and east are about (``lat_deg``, ``lon_deg``). Down is about the ground the drone took off from:
    every altitude (plans, setpoints, recorded states) is height above the autopilot's home, which PX4 sets
    where it armed (the ground is taken as flat across the flight area). ``alt_m`` is kept for reference (the
    ground's altitude AMSL at the origin; it is not used for heights). The autopilot's local NED frame is about
    its own EKF origin; the agent converts with the vehicle's global position and its height above home.
    Default: PX4 SITL's field, the built-in simulator's default origin.
    """

    lat_deg: float = 47.397742
    lon_deg: float = 8.545594
    alt_m: float = 488.0


@dataclass
class FormationFailsafeConfig:
    """Failsafes of the formation in track mode (:mod:`onboard.formation.failsafe`), checked every control step.

    Person lost (no accepted detection for ``person_lost_after_s``; before the first one, ``acquire_grace_s``
    after the formation's start) -> hold and turn at ``search_yaw_rate_deg_s`` to look; a teammate silent
    (no state or plan) for ``teammate_lost_after_s`` -> re-space the formation among the drones present;
    predicted separation below the plan's minimum + ``separation_margin_m`` or geofence margin below
    ``geofence_margin_m``, or ``max_consecutive_fallbacks`` MPC fallbacks in a row -> brake and hold; battery
    at ``battery_return_frac`` -> return, at ``battery_land_frac`` -> land. Ground-station loss stays with
    ``safety.gcs_heartbeat_timeout_s`` / ``safety.gcs_loss_action``.
    """

    enabled: bool = True
    person_lost_after_s: float = 3.0
    acquire_grace_s: float = 20.0
    teammate_lost_after_s: float = 2.0
    separation_margin_m: float = 0.5
    geofence_margin_m: float = 0.5
    max_consecutive_fallbacks: int = 5
    battery_return_frac: float = 0.25
    battery_land_frac: float = 0.12
    search_yaw_rate_deg_s: float = 30.0


@dataclass
class TrackConfig:
    """Active capture (``mode = "track"``): cooperative person tracking and the formation MPC.

    The plan's ``center_ned_m`` is the operator's approximate start position of the person (flown to until
    the first detection is fused), ``radius_m`` / ``altitude_m`` the distance and height kept from the
    person, ``phase_offset_rad`` the slot angles, ``min_separation_m`` the separation limit.
    """

    #: where this drone's own detections come from: "sim" = the simulator's box detector
    #: (``<drone>/sim/detections``, labelled ``detector="simulated"``); "onnx" = the ONNX person detector
    #: (``onboard/detector``, model ``detector_model``) on this drone's camera frames (``<drone>/camera/image``),
    #: in the region of interest the filter predicts (a worker thread, newest frame wins); "auto" (default) =
    #: "onnx" whenever a real camera is configured (``camera.source`` not "sim"), else "sim"
    detections: str = "auto"
    detector_model: str = "nanodet"
    detector_threads: int = 1  #: onnxruntime intra-op threads of the detector
    mpc_horizon_steps: int = 15
    mpc_dt_s: float = 0.1
    max_speed_h_m_s: float = 5.0
    person_keepout_m: float = 4.0
    #: this drone's position / attitude uncertainty (1 sigma) sent with its detections (GNSS grade: ~1 m GPS,
    #: ~0.05 m RTK)
    camera_position_sigma_m: float = 1.0
    camera_rotation_sigma_rad: float = 0.017
    #: use the drone's reported position accuracy (``VehicleState.position_cov_m2``: the receiver's horizontal /
    #: vertical accuracy, or the message's 1 m^2 default when the autopilot reports none) instead of
    #: ``camera_position_sigma_m`` for the own detections' pose covariance and the own offset's prior
    camera_cov_from_state: bool = True
    #: the person's height as the detector's box sees it (head top to feet, m): the range prior of the
    #: height-prior measurement and the ROI size (an operator enters the subject's height)
    person_height_m: float = 1.69
    #: stationary std of the person's velocity in the filter (walking: ~1 m/s)
    person_velocity_sigma_m_s: float = 1.0
    #: TargetEstimate publishing rate on ``<drone>/target``
    target_publish_hz: float = 10.0
    #: teammate plans/states older than this are not avoided (s)
    plan_timeout_s: float = 1.0
    failsafe: FormationFailsafeConfig = field(default_factory=FormationFailsafeConfig)
    #: GPS jump detection: a reported position step this far (m) beyond what the reported velocity explains
    #: counts as a jump of the position estimate; the step is then taken back from this drone's camera poses and
    #: planning position, relaxing to zero with time constant ``gps_jump_relax_s`` while the filter's own-offset
    #: estimate takes it over (so the drone stays in the fleet's frame). 0 = off
    gps_jump_threshold_m: float = 1.5
    gps_jump_relax_s: float = 30.0


@dataclass
class AgentConfig:
    """Top-level configuration of one drone's agent."""

    drone_id: str = "drone_1"
    fleet: str = "default"
    #: MAVSDK connection URL of the autopilot (PX4 SITL instance i: udpin://0.0.0.0:14540+i)
    connection: str = "udpin://0.0.0.0:14540"
    #: seconds to wait for the autopilot to appear
    connect_timeout_s: float = 30.0
    origin: OriginConfig = field(default_factory=OriginConfig)
    autopilot: AutopilotConfig = field(default_factory=AutopilotConfig)
    rates: RatesConfig = field(default_factory=RatesConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    flight: FlightConfig = field(default_factory=FlightConfig)
    record: RecordConfig = field(default_factory=RecordConfig)
    #: Zenoh session (default: a local peer joining the rendezvous at tcp/127.0.0.1:7447)
    transport: TransportConfig = field(default_factory=TransportConfig)
    #: record the simulator's keypoints (sim/keypoints2d) and camera frames of this drone
    record_camera: bool = True
    #: the drone's camera: "sim" (the simulator's camera node) or a real source captured on board
    camera: CameraConfig = field(default_factory=CameraConfig)
    #: "orbit" (fly the plan's circle around its centre) or "track" (find and follow the person: detections
    #: -> cooperative filter -> formation MPC around the fused estimate; see :class:`TrackConfig`)
    mode: str = "orbit"
    track: TrackConfig = field(default_factory=TrackConfig)

    def validate(self) -> "AgentConfig":
        self.camera.validate()
        self.autopilot.validate()
        if self.mode not in ("orbit", "track"):
            raise ConfigError(f"mode={self.mode!r}; use 'orbit' or 'track'")
        if self.track.detections not in ("auto", "sim", "onnx"):
            raise ConfigError(f"track.detections={self.track.detections!r}: use 'auto', 'sim' (the simulator's detector "
                              "on sim/detections) or 'onnx' (the ONNX person detector on the camera frames)")
        if self.track.detections == "auto":
            self.track.detections = "sim" if self.camera.source == "sim" else "onnx"
        if self.track.detections == "sim" and self.camera.source != "sim":
            raise ConfigError(f"track.detections='sim' with camera.source={self.camera.source!r}: the simulator's box "
                              "detector exists only in simulation; use 'onnx' (or 'auto') with a real camera")
        if self.track.detector_threads < 1:
            raise ConfigError(f"track.detector_threads={self.track.detector_threads}: must be >= 1")
        for name in ("gcs_loss_action", "low_battery_action"):
            v = getattr(self.safety, name)
            if v not in ("land", "return", "hold"):
                raise ConfigError(f"safety.{name}={v!r}; use 'land', 'return' or 'hold'")
        if self.safety.separation_action not in ("hold", "land", "warn"):
            raise ConfigError(f"safety.separation_action={self.safety.separation_action!r}; use 'hold', 'land' or 'warn'")
        if self.safety.sigterm_action not in ("land", "hold"):
            raise ConfigError(f"safety.sigterm_action={self.safety.sigterm_action!r}; use 'land' or 'hold'")
        if self.safety.on_restart_airborne not in ("land", "resume"):
            raise ConfigError(f"safety.on_restart_airborne={self.safety.on_restart_airborne!r}; use 'land' or 'resume'")
        if self.rates.setpoint_hz < 2:
            raise ConfigError(f"rates.setpoint_hz={self.rates.setpoint_hz}: PX4 offboard needs >= 2 Hz; use 10-50")
        f = self.track.failsafe
        if not (f.person_lost_after_s > 0 and f.teammate_lost_after_s > 0 and f.acquire_grace_s >= 0):
            raise ConfigError("track.failsafe: person_lost_after_s and teammate_lost_after_s must be > 0, "
                              "acquire_grace_s >= 0 (seconds)")
        if not 0 <= f.battery_land_frac <= f.battery_return_frac < 1:
            raise ConfigError(f"track.failsafe: need 0 <= battery_land_frac ({f.battery_land_frac}) <= "
                              f"battery_return_frac ({f.battery_return_frac}) < 1")
        if not 0 < self.safety.min_altitude_m < self.safety.max_altitude_m:
            raise ConfigError("safety.min_altitude_m must be > 0 and below safety.max_altitude_m")
        return self

