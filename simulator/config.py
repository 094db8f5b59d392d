"""Typed configuration of the built-in simulator's vehicles (``skycap sim``).

Loaded like every skycap config::

    cfg = load_config(SimConfig, path="sim.toml", overrides=["vehicles.count=3", "wind.mean_speed_m_s=4"])

Ports follow PX4 SITL: vehicle ``i`` (0-based) has MAVLink system id ``i + 1`` and sends its
offboard/API stream from local UDP port ``ports.local_base + i`` to ``ports.offboard_base + i`` on
``ports.host`` (the onboard agent listens with ``udpin://0.0.0.0:14540+i``), and a ground-station stream
to ``ports.gcs_port`` (0 disables it). Tests use other bases so they can run beside a demo.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from simulator.scene.person import PersonMotionConfig
from skycap.config import ConfigError


@dataclass
class OriginConfig:
    """Geodetic origin of the local NED world frame (WGS-84, altitude AMSL)."""

    lat_deg: float = 47.397742  # PX4 SITL default field (Zurich Irchel park)
    lon_deg: float = 8.545594
    alt_m: float = 488.0


@dataclass
class VehiclesConfig:
    """How many multirotors and where they stand at start (NED metres, on the ground: down = 0)."""

    count: int = 1
    #: explicit spawn positions [[north_m, east_m], ...]; empty -> a line along east, ``spacing_m`` apart
    spawn_ne_m: list[list[float]] = field(default_factory=list)
    spacing_m: float = 3.0
    #: initial heading of every vehicle (0 = north)
    spawn_yaw_deg: float = 0.0
    #: like PX4, each vehicle's LOCAL_POSITION_NED (and offboard NED setpoints) is relative to its own
    #: EKF origin = where it got its first GPS fix (its spawn point). False: relative to the world origin.
    local_origin_at_spawn: bool = True


@dataclass
class LimitsConfig:
    """Flight envelope, like the PX4 multicopter position-control parameters (MPC_*)."""

    max_speed_xy_m_s: float = 12.0  # MPC_XY_VEL_MAX
    max_speed_up_m_s: float = 3.0  # MPC_Z_VEL_MAX_UP
    max_speed_down_m_s: float = 1.5  # MPC_Z_VEL_MAX_DN
    max_accel_xy_m_s2: float = 5.0  # MPC_ACC_HOR_MAX
    #: horizontal acceleration of the auto modes' trajectories (takeoff, hold, return)
    auto_accel_xy_m_s2: float = 3.0  # MPC_ACC_HOR
    max_accel_z_m_s2: float = 4.0  # MPC_ACC_UP_MAX
    max_tilt_deg: float = 45.0  # MPC_TILTMAX_AIR
    max_yaw_rate_deg_s: float = 60.0  # MPC_YAWRAUTO_MAX
    #: first-order time constant of the attitude loop (how fast the real tilt follows the commanded tilt)
    attitude_time_constant_s: float = 0.08
    #: linear drag coefficient per unit mass [1/s] (air resistance relative to the air mass)
    drag_per_mass_1_s: float = 0.25


@dataclass
class ControllerConfig:
    """PX4's cascaded position (P) -> velocity (PID, acceleration units) controller gains; defaults = PX4's
    (the autopilot's parameters of the same meaning, named in the comments, override them at run time)."""

    pos_xy_p: float = 0.95  # MPC_XY_P
    pos_z_p: float = 1.0  # MPC_Z_P
    vel_xy_p: float = 1.8  # MPC_XY_VEL_P_ACC
    vel_xy_i: float = 0.4  # MPC_XY_VEL_I_ACC
    vel_xy_d: float = 0.2  # MPC_XY_VEL_D_ACC
    vel_z_p: float = 4.0  # MPC_Z_VEL_P_ACC
    vel_z_i: float = 2.0  # MPC_Z_VEL_I_ACC
    vel_z_d: float = 0.0  # MPC_Z_VEL_D_ACC
    #: low-pass cut-off of the velocity derivative (D term)
    vel_deriv_lp_hz: float = 5.0  # MPC_VELD_LP
    yaw_p: float = 2.8  # MC_YAW_P


@dataclass
class WindConfig:
    """Wind (NED, towards which it blows) with Gauss-Markov gusts. Default: still air."""

    mean_speed_m_s: float = 0.0
    #: direction the wind blows FROM, degrees from north (meteorological convention)
    from_direction_deg: float = 270.0
    gust_std_m_s: float = 0.0
    gust_time_constant_s: float = 2.0


@dataclass
class EstimatorConfig:
    """Errors of the vehicle's own pose estimate (what MAVLink reports); the truth is kept apart."""

    #: stationary std of the horizontal position bias (first-order Gauss-Markov), metres
    pos_bias_std_xy_m: float = 1.0
    pos_bias_std_z_m: float = 0.5
    #: correlation time of the position bias (slow drift), seconds
    pos_bias_time_constant_s: float = 60.0
    #: white noise on reported positions, metres (per sample)
    pos_noise_std_m: float = 0.02
    #: std of the attitude error per axis (slowly varying, correlation time below), degrees
    att_noise_std_deg: float = 1.0
    att_noise_time_constant_s: float = 1.0
    vel_noise_std_m_s: float = 0.05
    #: seconds after start until GPS has a 3D fix (health flags turn OK, home is set)
    gps_lock_delay_s: float = 1.0
    seed: int = 0


#: position-estimate grades -> the :class:`EstimatorConfig` fields they set (the rest keep their defaults): "gps" =
#: the defaults (m-level Gauss-Markov bias), "rtk" = cm-level bias, as a motion-capture fleet flies. The one source
#: of these numbers for the demo (``skycap demo --set rtk=...``) and the evaluation harness (``position_grade``).
POSITION_GRADES: dict[str, dict[str, float]] = {
    "gps": {},
    "rtk": {"pos_bias_std_xy_m": 0.02, "pos_bias_std_z_m": 0.03},
}


def estimator_for_grade(grade: str, base: EstimatorConfig | None = None) -> EstimatorConfig:
    """``base`` (default: the defaults) with the position grade's fields set (:data:`POSITION_GRADES`)."""
    import dataclasses

    if grade not in POSITION_GRADES:
        raise ConfigError(f"position grade {grade!r}; use one of {', '.join(repr(g) for g in POSITION_GRADES)}")
    return dataclasses.replace(base or EstimatorConfig(), **POSITION_GRADES[grade])


def grade_overrides(grade: str) -> list[str]:
    """The ``skycap sim --set`` overrides of a position grade (``estimator.<field>=<value>``)."""
    estimator_for_grade(grade)  # validates the name
    return [f"estimator.{k}={v}" for k, v in POSITION_GRADES[grade].items()]


@dataclass
class BatteryConfig:
    """A simple linear battery: drains at ``hover_drain_pct_per_min`` while armed, idle rate otherwise."""

    start_percent: float = 100.0
    hover_drain_pct_per_min: float = 4.0
    idle_drain_pct_per_min: float = 0.05
    cells: int = 4
    capacity_mah: float = 5000.0
    #: below this a warning STATUSTEXT is sent (PX4 BAT_LOW_THR), 0 disables
    low_percent: float = 15.0
    #: below this arming is denied and a flying vehicle returns home (PX4 BAT_CRIT_THR with
    #: COM_LOW_BAT_ACT = Return), 0 disables
    critical_percent: float = 7.0


@dataclass
class PortsConfig:
    """UDP ports as PX4 SITL: sends to ``offboard_base + i``, binds ``local_base + i``, GCS at ``gcs_port``."""

    host: str = "127.0.0.1"
    offboard_base: int = 14540
    #: 0 = let the OS pick free local ports (tests)
    local_base: int = 14580
    #: ground-station stream target (QGroundControl listens on 14550); 0 disables
    gcs_port: int = 14550
    gcs_local_base: int = 18570


@dataclass
class RatesConfig:
    """MAVLink stream rates (Hz) on the offboard link; MAV_CMD_SET_MESSAGE_INTERVAL changes them at run time."""

    heartbeat_hz: float = 1.0
    sys_status_hz: float = 2.0
    battery_hz: float = 1.0
    extended_sys_state_hz: float = 5.0
    attitude_hz: float = 50.0
    attitude_quaternion_hz: float = 50.0
    local_position_hz: float = 50.0
    global_position_hz: float = 50.0
    gps_raw_hz: float = 10.0
    home_position_hz: float = 0.5
    vfr_hud_hz: float = 4.0
    system_time_hz: float = 1.0
    #: EKF origin (sent on request by default, as PX4 does on the onboard link)
    gps_global_origin_hz: float = 0.0
    #: ODOMETRY (local NED pose + body-frame velocity), off unless requested (MAVSDK set_rate_odometry)
    odometry_hz: float = 0.0
    #: gimbal protocol v2 streams (only sent by a vehicle with a gimbal; PX4's onboard rates)
    gimbal_device_attitude_status_hz: float = 10.0
    gimbal_manager_status_hz: float = 5.0


#: offboard-loss actions by name -> PX4 COM_OBL_RC_ACT value
OFFBOARD_LOSS_ACTIONS = {"position": 0, "altitude": 1, "stabilized": 2, "return": 3, "land": 4, "hold": 5,
                         "terminate": 6, "disarm": 7}


@dataclass
class FailsafeConfig:
    """PX4 commander behaviour (COM_* parameters)."""

    #: COM_OF_LOSS_T: offboard setpoints older than this -> failsafe
    offboard_loss_timeout_s: float = 1.0
    #: what to do on offboard loss (COM_OBL_RC_ACT): "position" (PX4's default 0: Position mode, which needs RC
    #: this simulator has not, so Return), "altitude" (1) and "stabilized" (2) likewise Return, "return" (3),
    #: "land" (4), "hold" (5), "terminate" (6) / "disarm" (7): motors off where it is
    offboard_loss_action: str = "position"
    #: COM_DISARM_LAND: disarm this long after landing (<0 disables)
    disarm_after_land_s: float = 2.0
    #: COM_DISARM_PRFLT: disarm if armed on the ground without taking off for this long (<0 disables)
    disarm_preflight_s: float = 10.0


@dataclass
class GimbalConfig:
    """One camera gimbal per simulated vehicle (dynamics: :mod:`simulator.vehicle.gimbal`)."""

    #: False: the vehicles have no gimbal (no gimbal messages; MAVSDK discovers none)
    enabled: bool = True
    #: pitch limits (deg, relative to the horizon; negative = down)
    pitch_min_deg: float = -90.0
    pitch_max_deg: float = 30.0
    #: yaw limits (deg, relative to the vehicle heading)
    yaw_min_deg: float = -180.0
    yaw_max_deg: float = 180.0
    #: rate limit of each axis (deg/s)
    max_rate_deg_s: float = 90.0
    #: first-order lag of each axis towards its target (s)
    time_constant_s: float = 0.1
    #: pitch the gimbal starts at (deg; ``skycap sim --gimbal-pitch-deg``)
    initial_pitch_deg: float = 0.0
    vendor_name: str = "skycap"
    model_name: str = "sim-gimbal-2axis"

    def validate(self) -> "GimbalConfig":
        if not self.pitch_min_deg < self.pitch_max_deg or not self.yaw_min_deg < self.yaw_max_deg:
            raise ConfigError(f"gimbal limits: pitch {self.pitch_min_deg}..{self.pitch_max_deg} deg, yaw "
                              f"{self.yaw_min_deg}..{self.yaw_max_deg} deg; each min must be below its max")
        if self.max_rate_deg_s <= 0 or self.time_constant_s < 0:
            raise ConfigError(f"gimbal.max_rate_deg_s={self.max_rate_deg_s} must be > 0 and "
                              f"gimbal.time_constant_s={self.time_constant_s} >= 0")
        if not self.pitch_min_deg <= self.initial_pitch_deg <= self.pitch_max_deg:
            raise ConfigError(f"gimbal.initial_pitch_deg={self.initial_pitch_deg} is outside the pitch limits "
                              f"{self.pitch_min_deg}..{self.pitch_max_deg} deg")
        return self


@dataclass
class SimConfig:
    """Top-level configuration of ``skycap sim``."""

    vehicles: VehiclesConfig = field(default_factory=VehiclesConfig)
    origin: OriginConfig = field(default_factory=OriginConfig)
    limits: LimitsConfig = field(default_factory=LimitsConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    wind: WindConfig = field(default_factory=WindConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    battery: BatteryConfig = field(default_factory=BatteryConfig)
    ports: PortsConfig = field(default_factory=PortsConfig)
    rates: RatesConfig = field(default_factory=RatesConfig)
    failsafe: FailsafeConfig = field(default_factory=FailsafeConfig)
    #: one camera gimbal per vehicle (MAVLink gimbal protocol v2; ``gimbal.enabled=false``: none)
    gimbal: GimbalConfig = field(default_factory=GimbalConfig)
    #: the person performs this recorded motion (``--motion FILE.bvh``; simulator.scene.person): "" = the default
    #: walk with stops
    motion: PersonMotionConfig = field(default_factory=PersonMotionConfig)
    #: physics / controller step rate
    physics_hz: float = 100.0
    #: default takeoff altitude (PX4 MIS_TAKEOFF_ALT), metres above home
    takeoff_alt_m: float = 2.5
    #: Return's highest return altitude above home (PX4 RTL_RETURN_ALT); nearer home the cone below lowers it
    rtl_return_alt_m: float = 60.0
    #: Return descends to this height above home before landing (PX4 RTL_DESCEND_ALT)
    rtl_descend_alt_m: float = 30.0
    #: half-angle of PX4's return-altitude cone over home (RTL_CONE_ANG; 0: always RTL_RETURN_ALT)
    rtl_cone_half_angle_deg: float = 45.0
    #: horizontal speed of Return and goto (PX4 MPC_XY_CRUISE)
    cruise_speed_m_s: float = 5.0

    def validate(self) -> "SimConfig":
        """Raise :class:`ConfigError` on values the simulator cannot run with; returns self."""
        self.motion.validate()
        if self.vehicles.count < 1 or self.vehicles.count > 250:
            raise ConfigError(f"vehicles.count={self.vehicles.count} must be in 1..250 (MAVLink system ids)")
        if self.vehicles.spawn_ne_m and len(self.vehicles.spawn_ne_m) < self.vehicles.count:
            raise ConfigError(
                f"vehicles.spawn_ne_m lists {len(self.vehicles.spawn_ne_m)} positions for "
                f"{self.vehicles.count} vehicles; give one [north_m, east_m] per vehicle or leave it empty"
            )
        for p in self.vehicles.spawn_ne_m:
            if len(p) != 2:
                raise ConfigError(f"vehicles.spawn_ne_m entry {p} must be [north_m, east_m]")
        if self.physics_hz < 50:
            raise ConfigError(f"physics_hz={self.physics_hz} is too low; use >= 100")
        if self.failsafe.offboard_loss_action not in OFFBOARD_LOSS_ACTIONS:
            raise ConfigError(
                f"failsafe.offboard_loss_action={self.failsafe.offboard_loss_action!r}; use one of "
                f"{', '.join(repr(a) for a in OFFBOARD_LOSS_ACTIONS)} (PX4 COM_OBL_RC_ACT 0..7)"
            )
        if not 0 <= self.rtl_cone_half_angle_deg <= 90:
            raise ConfigError(f"rtl_cone_half_angle_deg={self.rtl_cone_half_angle_deg} must be in 0..90 (RTL_CONE_ANG)")
        self.gimbal.validate()
        if not 0 < self.limits.max_tilt_deg < 80:
            raise ConfigError(f"limits.max_tilt_deg={self.limits.max_tilt_deg} must be in (0, 80)")
        for name in ("offboard_base", "local_base", "gcs_local_base"):
            base = getattr(self.ports, name)
            if name != "offboard_base" and base == 0:  # 0 = any free port
                continue
            if not 1 <= base <= 65535 - self.vehicles.count:
                raise ConfigError(f"ports.{name}={base} leaves no room for {self.vehicles.count} vehicles")
        return self

    def spawn_ned_m(self, index: int) -> tuple[float, float, float]:
        """Spawn position of vehicle ``index`` (NED metres, on the ground)."""
        if self.vehicles.spawn_ne_m:
            n, e = self.vehicles.spawn_ne_m[index]
            return float(n), float(e), 0.0
        return 0.0, index * self.vehicles.spacing_m, 0.0
