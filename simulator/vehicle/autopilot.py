"""One simulated PX4 multirotor without I/O: commander (modes, arming, failsafes), controller, dynamics,
estimator errors, battery. The MAVLink endpoint (:mod:`simulator.vehicle.mavlink_endpoint`) is a thin
adapter that turns messages into the calls below and the state below into messages.

Frames: the *world* frame is the simulator's NED frame about ``cfg.origin`` (truth and estimate live
there). The vehicle's *local* frame (LOCAL_POSITION_NED, offboard NED setpoints) is the world frame
shifted to the EKF origin ``local_origin_ned_m`` (the spawn point, as PX4, unless
``vehicles.local_origin_at_spawn = false``).

Times are seconds since the simulation started (monotonic), passed in by the caller.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np

from simulator.config import OFFBOARD_LOSS_ACTIONS, SimConfig
from simulator.vehicle.controller import AutoTrajectory, ControllerLimits, PositionController, TrajectorySetpoint
from simulator.vehicle.dynamics import GRAVITY_M_S2, DynamicsLimits, MultirotorDynamics
from simulator.vehicle.environment import Battery, EstimatorErrorModel
from simulator.vehicle.gimbal import SimGimbal
from simulator.vehicle.params import MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32, Param, ParamStore
from simulator.vehicle.px4_modes import MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, FlightMode, flight_mode_from_px4
from skycap.frames import ned_to_geodetic, yaw_from_R

log = logging.getLogger(__name__)

# MAV_RESULT
ACCEPTED, TEMPORARILY_REJECTED, DENIED, UNSUPPORTED, FAILED = 0, 1, 2, 3, 4
# MAV_LANDED_STATE
LANDED_UNDEFINED, LANDED_ON_GROUND, LANDED_IN_AIR, LANDED_TAKEOFF, LANDED_LANDING = 0, 1, 2, 3, 4
FORCE_MAGIC = 21196.0
#: an Offboard switch this soon before the takeoff completes is overridden by the takeoff's Hold (PX4: the
#: navigator and the commander run asynchronously, ~10 Hz; a model of that race, not a measured figure)
TAKEOFF_RACE_S = 0.1

# PX4 COM_OBL_RC_ACT values
OBL_POSITION, OBL_ALTITUDE, OBL_STABILIZED, OBL_RETURN, OBL_LAND, OBL_HOLD, OBL_TERMINATE, OBL_DISARM = range(8)


@dataclass
class VehicleSnapshot:
    """The simulator's state of one vehicle at one instant, world NED frame (plus what the autopilot believes):
    the truth that :class:`simulator.truth.TruthPublisher` publishes as ``shared_msgs.VehicleTruth``.

    Shapes: positions/velocities/accelerations (3,), rotations (3,3) body FRD -> world NED.
    """

    index: int
    system_id: int
    #: wall-clock time of the tick (``time.time_ns()``)
    t_ns: int
    position_ned_m: np.ndarray
    velocity_ned_m_s: np.ndarray
    R_world_body: np.ndarray
    armed: bool
    flight_mode: str
    landed: bool
    #: seconds since the simulation started (the MAVLink ``time_boot_ms`` clock)
    t_sim_s: float = 0.0
    accel_ned_m_s2: np.ndarray | None = None
    angular_velocity_body_rad_s: np.ndarray | None = None
    #: the vehicle's own estimate (what it reports over MAVLink), in the world frame
    est_position_ned_m: np.ndarray | None = None
    est_R_world_body: np.ndarray | None = None
    battery_percent: float = 100.0
    #: the gimbal's true attitude (pitch relative to the horizon, yaw relative to the heading); None: no gimbal
    gimbal_pitch_rad: float | None = None
    gimbal_yaw_rad: float | None = None


def default_params(cfg: SimConfig, system_id: int) -> list[Param]:
    """The PX4 parameters this simulator honours (names and units as PX4)."""
    L, F, G = cfg.limits, cfg.failsafe, cfg.controller
    R, INT = MAV_PARAM_TYPE_REAL32, MAV_PARAM_TYPE_INT32
    return [
        Param("MIS_TAKEOFF_ALT", cfg.takeoff_alt_m, R),
        Param("NAV_MC_ALT_RAD", 0.8, R),  # takeoff complete this far below its altitude
        Param("MPC_XY_VEL_MAX", L.max_speed_xy_m_s, R),
        Param("MPC_XY_CRUISE", cfg.cruise_speed_m_s, R),
        Param("MPC_Z_VEL_MAX_UP", L.max_speed_up_m_s, R),
        Param("MPC_Z_VEL_MAX_DN", L.max_speed_down_m_s, R),
        Param("MPC_Z_V_AUTO_DN", min(1.5, L.max_speed_down_m_s), R),
        Param("MPC_ACC_HOR_MAX", L.max_accel_xy_m_s2, R),
        Param("MPC_ACC_HOR", L.auto_accel_xy_m_s2, R),
        Param("MPC_ACC_UP_MAX", L.max_accel_z_m_s2, R),
        Param("MPC_TILTMAX_AIR", L.max_tilt_deg, R),
        Param("MPC_YAWRAUTO_MAX", L.max_yaw_rate_deg_s, R),
        Param("MPC_TKO_SPEED", min(1.5, L.max_speed_up_m_s), R),
        Param("MPC_LAND_SPEED", min(0.7, L.max_speed_down_m_s), R),
        Param("MPC_LAND_ALT1", 10.0, R),
        Param("MPC_LAND_ALT2", 5.0, R),
        Param("MPC_XY_P", G.pos_xy_p, R),
        Param("MPC_Z_P", G.pos_z_p, R),
        Param("MPC_XY_VEL_P_ACC", G.vel_xy_p, R),
        Param("MPC_XY_VEL_I_ACC", G.vel_xy_i, R),
        Param("MPC_XY_VEL_D_ACC", G.vel_xy_d, R),
        Param("MPC_Z_VEL_P_ACC", G.vel_z_p, R),
        Param("MPC_Z_VEL_I_ACC", G.vel_z_i, R),
        Param("MPC_Z_VEL_D_ACC", G.vel_z_d, R),
        Param("MPC_VELD_LP", G.vel_deriv_lp_hz, R),
        Param("MC_YAW_P", G.yaw_p, R),
        Param("RTL_RETURN_ALT", cfg.rtl_return_alt_m, R),
        Param("RTL_DESCEND_ALT", cfg.rtl_descend_alt_m, R),
        Param("RTL_CONE_ANG", int(round(cfg.rtl_cone_half_angle_deg)), INT),
        Param("COM_OF_LOSS_T", F.offboard_loss_timeout_s, R),
        Param("COM_OBL_RC_ACT", OFFBOARD_LOSS_ACTIONS[F.offboard_loss_action], INT),
        Param("COM_DISARM_LAND", F.disarm_after_land_s, R),
        Param("COM_DISARM_PRFLT", F.disarm_preflight_s, R),
        # RC / data-link loss: accepted and reported like PX4 (this simulator has neither link to lose)
        Param("NAV_RCL_ACT", 2, INT),
        Param("NAV_DLL_ACT", 0, INT),
        Param("COM_RCL_EXCEPT", 0, INT),
        Param("BAT_LOW_THR", cfg.battery.low_percent / 100.0, R),
        Param("BAT_CRIT_THR", cfg.battery.critical_percent / 100.0, R),
        Param("MAV_SYS_ID", system_id, INT),
        Param("SYS_AUTOSTART", 4001, INT),  # x500-class quadrotor airframe
        Param("COM_RC_IN_MODE", 3, INT),  # PX4's default; no RC is ever connected here
    ]


class SimVehicle:
    """One PX4-like multirotor. Drive it with :meth:`step`; command it with the ``cmd_*`` / setpoint methods.

    Args:
        index: 0-based vehicle index (system id = index + 1).
        cfg: the simulator configuration (validated).
        seed: randomness of the estimator errors.
    """

    def __init__(self, index: int, cfg: SimConfig, seed: int | None = None):
        self.index = index
        self.system_id = index + 1
        self.cfg = cfg
        spawn = np.array(cfg.spawn_ned_m(index), dtype=float)
        self.spawn_ned_m = spawn
        self.local_origin_ned_m = spawn.copy() if cfg.vehicles.local_origin_at_spawn else np.zeros(3)
        L = cfg.limits
        self.dyn = MultirotorDynamics(
            DynamicsLimits(
                max_tilt_rad=math.radians(L.max_tilt_deg) * 1.05,  # airframe can tilt a bit more than commanded
                max_yaw_rate_rad_s=math.radians(L.max_yaw_rate_deg_s) * 1.5,
                attitude_time_constant_s=L.attitude_time_constant_s,
                drag_per_mass_1_s=L.drag_per_mass_1_s,
            ),
            position_ned_m=spawn,
            yaw_rad=math.radians(cfg.vehicles.spawn_yaw_deg),
        )
        # a copy: parameters change this vehicle's gains, not the shared config
        self.ctrl = PositionController(ControllerLimits.from_config(L), dataclasses.replace(cfg.controller))
        self.traj = AutoTrajectory(spawn)
        self.est_model = EstimatorErrorModel(
            cfg.estimator, seed=cfg.estimator.seed * 1000 + index if seed is None else seed
        )
        self.battery = Battery(cfg.battery)
        #: the camera gimbal (None: ``gimbal.enabled = false``)
        self.gimbal: SimGimbal | None = SimGimbal(cfg.gimbal) if cfg.gimbal.enabled else None
        self.params = ParamStore(default_params(cfg, self.system_id), on_change=self._on_param_change)
        self._apply_params()

        self.t_s = 0.0
        self._dt_s = 1.0 / cfg.physics_hz
        self.armed = False
        self.mode = FlightMode.HOLD
        self.gps_ok = False
        self.home_ned_m: np.ndarray | None = None  # world frame (estimate), set at GPS fix and on arming
        #: recent (MAV_SEVERITY, text) messages, newest last (each MAVLink link sends the ones it has not sent)
        self.status_texts: list[tuple[int, str]] = []
        self.status_count = 0  # how many were ever said
        self._armed_at_s = 0.0
        self._has_flown = False
        self._landed_since_s: float | None = 0.0
        self._hold_target: np.ndarray | None = None
        self._hold_speed_m_s = math.nan
        self._hold_yaw = math.nan
        self._takeoff_target: np.ndarray | None = None
        #: when an Offboard switch left Takeoff: if the takeoff completes within TAKEOFF_RACE_S after it, PX4's
        #: "takeoff complete" Hold wins over the switch
        self._offboard_from_takeoff_t_s = -math.inf
        self._land_xy: np.ndarray | None = None
        self._rtl_phase = ""
        self._rtl_alt_d = 0.0
        self._rtl_descend_d = 0.0
        #: the current mode is the offboard-loss failsafe's: back to Offboard when setpoints resume (PX4)
        self._offboard_failsafe = False
        self._offboard_sp: TrajectorySetpoint | None = None
        self._offboard_sp_t_s = -math.inf
        self._battery_failsafe_done = False
        self._battery_low_warned = False
        #: scheduled GPS jumps [(sim time s, offset (3,))] (fault injection: :meth:`schedule_gps_jump`)
        self._gps_jumps: list[tuple[float, np.ndarray]] = []
        self.gps_jumps_done: list[tuple[float, tuple[float, float, float]]] = []
        self._update_estimate()

    def schedule_gps_jump(self, at_s: float, offset_ned_m) -> None:
        """Fault injection: at simulation time ``at_s`` the position estimate jumps by ``offset_ned_m`` (3,) m
        (the estimator's bias steps; the vehicle then flies its setpoints in the jumped frame)."""
        off = np.asarray(offset_ned_m, dtype=float).reshape(3)
        if not (math.isfinite(at_s) and np.all(np.isfinite(off))):
            raise ValueError(f"GPS jump needs a finite time and offset, got at_s={at_s}, offset={offset_ned_m!r}")
        self._gps_jumps = sorted([*self._gps_jumps, (float(at_s), off)], key=lambda j: j[0])

    # ------------------------------------------------------------------ parameters
    def _apply_params(self) -> None:
        p, lim, g = self.params, self.ctrl.limits, self.ctrl.gains
        g.pos_xy_p, g.pos_z_p = float(p["MPC_XY_P"]), float(p["MPC_Z_P"])
        g.vel_xy_p, g.vel_xy_i, g.vel_xy_d = (float(p["MPC_XY_VEL_P_ACC"]), float(p["MPC_XY_VEL_I_ACC"]),
                                              float(p["MPC_XY_VEL_D_ACC"]))
        g.vel_z_p, g.vel_z_i, g.vel_z_d = (float(p["MPC_Z_VEL_P_ACC"]), float(p["MPC_Z_VEL_I_ACC"]),
                                           float(p["MPC_Z_VEL_D_ACC"]))
        g.vel_deriv_lp_hz, g.yaw_p = float(p["MPC_VELD_LP"]), float(p["MC_YAW_P"])
        lim.max_speed_xy_m_s = float(p["MPC_XY_VEL_MAX"])
        lim.max_speed_up_m_s = float(p["MPC_Z_VEL_MAX_UP"])
        lim.max_speed_down_m_s = float(p["MPC_Z_VEL_MAX_DN"])
        lim.max_accel_xy_m_s2 = float(p["MPC_ACC_HOR_MAX"])
        lim.max_accel_z_m_s2 = float(p["MPC_ACC_UP_MAX"])
        lim.max_tilt_rad = math.radians(float(p["MPC_TILTMAX_AIR"]))
        lim.max_yaw_rate_rad_s = math.radians(float(p["MPC_YAWRAUTO_MAX"]))

    def _on_param_change(self, name: str, value) -> None:
        log.info("vehicle %d: param %s = %s", self.system_id, name, value)
        self._apply_params()

    # ------------------------------------------------------------------ state access
    @property
    def truth(self):
        return self.dyn.state

    @property
    def landed(self) -> bool:
        return self.dyn.state.on_ground

    def truth_snapshot(self, t_ns: int) -> VehicleSnapshot:
        s = self.dyn.state
        return VehicleSnapshot(
            index=self.index,
            system_id=self.system_id,
            t_ns=t_ns,
            position_ned_m=s.position_ned_m.copy(),
            velocity_ned_m_s=s.velocity_ned_m_s.copy(),
            R_world_body=s.R_world_body.copy(),
            armed=self.armed,
            flight_mode=self.mode.name,
            landed=s.on_ground,
            t_sim_s=self.t_s,
            accel_ned_m_s2=s.accel_ned_m_s2.copy(),
            angular_velocity_body_rad_s=s.angular_velocity_body_rad_s.copy(),
            est_position_ned_m=self.est_position_ned_m.copy(),
            est_R_world_body=self.est_R_world_body.copy(),
            battery_percent=self.battery.remaining_pct,
            gimbal_pitch_rad=None if self.gimbal is None else self.gimbal.pitch_rad,
            gimbal_yaw_rad=None if self.gimbal is None else self.gimbal.yaw_rad,
        )

    def _update_estimate(self) -> None:
        s = self.dyn.state
        self.est_position_ned_m, self.est_velocity_ned_m_s, self.est_R_world_body = self.est_model.estimate(
            s.position_ned_m, s.velocity_ned_m_s, s.R_world_body
        )
        self.est_yaw_rad = yaw_from_R(self.est_R_world_body)

    @property
    def est_local_position_ned_m(self) -> np.ndarray:
        return self.est_position_ned_m - self.local_origin_ned_m

    def geodetic(self, world_ned_m: np.ndarray) -> tuple[float, float, float]:
        o = self.cfg.origin
        lat, lon, alt = ned_to_geodetic(world_ned_m, o.lat_deg, o.lon_deg, o.alt_m)
        return float(lat), float(lon), float(alt)

    @property
    def landed_state(self) -> int:
        if self.landed:
            return LANDED_ON_GROUND
        if self.mode == FlightMode.TAKEOFF and self._takeoff_target is not None:
            # PX4's land detector says "in air" about half-way up the takeoff climb (1.4 of 2.5 m measured)
            home_d = self.home_ned_m[2] if self.home_ned_m is not None else self.spawn_ned_m[2]
            if home_d - self.est_position_ned_m[2] < 0.5 * (home_d - self._takeoff_target[2]):
                return LANDED_TAKEOFF
        if self.mode == FlightMode.LAND or (self.mode == FlightMode.RETURN and self._rtl_phase == "land"):
            return LANDED_LANDING
        return LANDED_IN_AIR

    def offboard_setpoint_fresh(self) -> bool:
        return self.t_s - self._offboard_sp_t_s <= float(self.params["COM_OF_LOSS_T"])

    def _say(self, severity: int, text: str) -> None:
        log.info("vehicle %d: %s", self.system_id, text)
        self.status_texts.append((severity, text))
        self.status_count += 1
        if len(self.status_texts) > 200:
            del self.status_texts[:100]

    # ------------------------------------------------------------------ commands (return MAV_RESULT)
    @property
    def prearm_ok(self) -> bool:
        """PX4's pre-arm checks as the SYS_STATUS PREARM bit reports them (MAVSDK ``is_armable``): GPS fix, battery,
        and in Offboard a live offboard signal -- e.g. a vehicle that landed from Offboard stays in Offboard and
        is not armable until setpoints stream again or another mode is set (measured on PX4)."""
        return (self.gps_ok and not self._battery_critical()
                and not (self.mode == FlightMode.OFFBOARD and not self.offboard_setpoint_fresh()))

    def cmd_arm(self, arm: bool, force: bool = False) -> int:
        if arm:
            if self.armed:
                return ACCEPTED
            if not force:
                if not self.gps_ok:
                    self._say(4, "Arming denied: no GPS fix")
                    return DENIED
                if self._battery_critical():
                    self._say(4, "Arming denied: battery critical")
                    return DENIED
                if self.mode == FlightMode.OFFBOARD and not self.offboard_setpoint_fresh():
                    self._say(4, "Arming denied: no offboard signal")
                    return DENIED
            self.armed = True
            self._armed_at_s = self.t_s
            self._has_flown = False
            self._landed_since_s = self.t_s if self.landed else None
            self.home_ned_m = self.est_position_ned_m.copy()  # PX4 sets home on arming
            self.ctrl.reset()
            self.traj.reset(self.est_position_ned_m)
            self._hold_target = None
            self._say(6, "Armed")
            return ACCEPTED
        if not self.armed:
            return ACCEPTED
        if not self.landed and not force:
            self._say(4, "Disarming denied: not landed")
            return DENIED
        self._disarm("Disarmed by command")
        return ACCEPTED

    def _disarm(self, why: str) -> None:
        self.armed = False
        self._say(6, why)

    def _commanded(self) -> None:
        """A mode was commanded (not chosen by a failsafe): the offboard-loss failsafe no longer owns the mode."""
        self._offboard_failsafe = False

    def cmd_takeoff(self, altitude_amsl_m: float = math.nan) -> int:
        if not self.armed:
            self._say(4, "Takeoff denied: disarmed")
            return TEMPORARILY_REJECTED
        self._commanded()
        home_d = self.home_ned_m[2] if self.home_ned_m is not None else self.est_position_ned_m[2]
        target_d = home_d - float(self.params["MIS_TAKEOFF_ALT"])
        if math.isfinite(altitude_amsl_m):
            requested_d = self.cfg.origin.alt_m - altitude_amsl_m
            if requested_d <= home_d - 1.0:
                target_d = requested_d
            else:  # e.g. 0 sent for "unset": climb to MIS_TAKEOFF_ALT instead of into the ground
                self._say(
                    4, f"Takeoff altitude {altitude_amsl_m:.1f} m AMSL is below home + 1 m; using MIS_TAKEOFF_ALT"
                )
        self._takeoff_target = np.array([self.est_position_ned_m[0], self.est_position_ned_m[1], target_d])
        self._set_mode(FlightMode.TAKEOFF)
        return ACCEPTED

    def cmd_land(self) -> int:
        self._commanded()
        self._set_mode(FlightMode.LAND)
        return ACCEPTED

    def cmd_return(self) -> int:
        if self.home_ned_m is None:
            return TEMPORARILY_REJECTED
        if not self.armed or self.landed:
            return TEMPORARILY_REJECTED
        self._commanded()
        self._set_mode(FlightMode.RETURN)
        return ACCEPTED

    def cmd_hold(self) -> int:
        self._commanded()
        self._set_mode(FlightMode.HOLD)
        return ACCEPTED

    def cmd_set_mode(self, base_mode: float, main_mode: float, sub_mode: float) -> int:
        """MAV_CMD_DO_SET_MODE with PX4 custom modes."""
        if not int(base_mode) & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return UNSUPPORTED
        fm = flight_mode_from_px4(int(main_mode), int(sub_mode))
        if fm is None:
            return UNSUPPORTED
        if fm == self.mode:
            self._commanded()
            return ACCEPTED
        if fm == FlightMode.HOLD:
            return self.cmd_hold()
        if fm == FlightMode.LAND:
            return self.cmd_land()
        if fm == FlightMode.RETURN:
            return self.cmd_return()
        if fm == FlightMode.TAKEOFF:
            return self.cmd_takeoff()
        if fm == FlightMode.OFFBOARD:
            if not self.offboard_setpoint_fresh():
                self._say(4, "Switching to Offboard is currently not available: no offboard signal")
                return TEMPORARILY_REJECTED
            self._commanded()
            if self.mode == FlightMode.TAKEOFF:
                self._offboard_from_takeoff_t_s = self.t_s
            self._set_mode(FlightMode.OFFBOARD)
            return ACCEPTED
        if fm == FlightMode.MISSION:
            self._say(4, "Mission rejected: no mission")
            return TEMPORARILY_REJECTED
        # manual modes need an RC link this simulator does not have
        self._say(4, f"Switching to {fm.name} is currently not available: no manual control input")
        return TEMPORARILY_REJECTED

    def cmd_reposition(self, world_ned_m: np.ndarray, yaw_rad: float = math.nan, speed_m_s: float = math.nan) -> int:
        """MAV_CMD_DO_REPOSITION (MAVSDK goto_location): fly to a point and hold there. NaN = keep."""
        if not self.armed or self.landed:
            return TEMPORARILY_REJECTED
        self._commanded()
        target = self.est_position_ned_m.copy() if self._hold_target is None else self._hold_target.copy()
        for k in range(3):
            if math.isfinite(world_ned_m[k]):
                target[k] = world_ned_m[k]
        self._set_mode(FlightMode.HOLD)
        self._hold_target = target
        self._hold_yaw = yaw_rad
        self._hold_speed_m_s = float(self.params["MPC_XY_CRUISE"]) if math.isnan(speed_m_s) else speed_m_s
        return ACCEPTED

    def cmd_change_speed(self, speed_m_s: float) -> int:
        if speed_m_s <= 0 or not math.isfinite(speed_m_s):
            return DENIED
        self._hold_speed_m_s = speed_m_s
        return ACCEPTED

    def set_offboard_setpoint(self, sp: TrajectorySetpoint) -> None:
        """A new offboard setpoint in the *local* frame (as received); refreshes the offboard signal."""
        if not np.all(np.isnan(sp.position_ned_m)):
            sp.position_ned_m = sp.position_ned_m + self.local_origin_ned_m
        self._offboard_sp = sp
        self._offboard_sp_t_s = self.t_s

    def _set_mode(self, mode: FlightMode) -> None:
        if mode == self.mode and mode != FlightMode.TAKEOFF:
            return
        prev = self.mode
        self.mode = mode
        self._hold_yaw = self.est_yaw_rad
        p = self.est_position_ned_m
        v = self.est_velocity_ned_m_s
        if prev in (FlightMode.OFFBOARD, FlightMode.LAND) or not self.armed:
            # the auto trajectory starts from where the vehicle is (an auto mode before it: continue smoothly)
            self.traj.reset(p, v)
        if mode == FlightMode.HOLD:
            # brake to a stop, then hold where it stopped (PX4 computes a braking point too)
            a = max(float(self.params["MPC_ACC_HOR"]) * 0.8, 0.5)
            vt = self.traj.velocity_ned_m_s
            self._hold_target = self.traj.position_ned_m + vt * np.abs(vt) / (2.0 * a) * np.array([1.0, 1.0, 0.0])
            self._hold_speed_m_s = math.nan
            self._hold_yaw = self.est_yaw_rad
        elif mode == FlightMode.LAND:
            self._land_xy = p[:2].copy()
        elif mode == FlightMode.RETURN:
            self._rtl_phase = "climb"
            self._rtl_alt_d, self._rtl_descend_d = self._rtl_altitudes_d(p)
        if prev != mode:
            log.info("vehicle %d: mode %s -> %s", self.system_id, prev.name, mode.name)

    def _rtl_altitudes_d(self, p: np.ndarray) -> tuple[float, float]:
        """(return altitude, descend altitude) as world down coordinates, as PX4's RTL computes them: the return
        altitude is RTL_RETURN_ALT above home, lowered near home to the cone RTL_CONE_ANG over home (at 8 m from
        home: ~8 m with the default 45 deg, measured on PX4), never below the current altitude; then descend to
        RTL_DESCEND_ALT above home if higher, then land."""
        P, home = self.params, self.home_ned_m
        ret_h = float(P["RTL_RETURN_ALT"])
        cone = float(P["RTL_CONE_ANG"])
        if 0.0 < cone < 90.0:
            dist = math.hypot(p[0] - home[0], p[1] - home[1])
            ret_h = min(ret_h, dist / math.tan(math.radians(cone)))
        ret_d = min(p[2], home[2] - ret_h)
        descend_d = max(ret_d, home[2] - float(P["RTL_DESCEND_ALT"]))
        return ret_d, descend_d

    def _battery_critical(self) -> bool:
        thr = float(self.params["BAT_CRIT_THR"]) * 100.0
        return thr > 0 and self.battery.remaining_pct <= thr

    # ------------------------------------------------------------------ simulation step
    def step(self, t_s: float, dt_s: float, wind_ned_m_s: np.ndarray) -> None:
        """Advance to ``t_s`` (seconds since start) by ``dt_s``: estimator, commander, controller, physics."""
        self.t_s = t_s
        self._dt_s = dt_s
        self.est_model.step(dt_s)
        while self._gps_jumps and self._gps_jumps[0][0] <= t_s:
            _, off = self._gps_jumps.pop(0)
            self.est_model.jump(off)
            self.gps_jumps_done.append((t_s, tuple(float(v) for v in off)))
            log.warning("vehicle %d: SIMULATED GPS JUMP of %s m (|%.2f| m) at t=%.2f s", self.system_id,
                        np.round(off, 2).tolist(), float(np.linalg.norm(off)), t_s)
            self._say(4, f"Simulated GPS jump {float(np.linalg.norm(off)):.1f} m")
        self._update_estimate()
        if not self.gps_ok and t_s >= self.cfg.estimator.gps_lock_delay_s:
            self.gps_ok = True
            self.home_ned_m = self.est_position_ned_m.copy()
            self._say(6, "GPS fix, home set")
        self._commander(t_s)
        sp = self._mode_setpoint()
        body_z, thrust, yaw_rate = self.ctrl.update(
            dt_s, sp, self.est_position_ned_m, self.est_velocity_ned_m_s, self.est_yaw_rad, self.landed,
            accel_ned_m_s2=self.dyn.state.accel_ned_m_s2,
        )
        if self.armed and self.landed and self._wants_ground(sp):
            thrust = min(thrust, 0.5 * GRAVITY_M_S2)  # idle on the ground
        self.dyn.step(dt_s, body_z, thrust, yaw_rate, wind_ned_m_s, motors_on=self.armed)
        self.battery.step(dt_s, self.armed, self.dyn.state.thrust_m_s2 / GRAVITY_M_S2)
        if self.gimbal is not None:
            self.gimbal.step(dt_s, yaw_from_R(self.dyn.state.R_world_body))

    def _wants_ground(self, sp: TrajectorySetpoint) -> bool:
        if sp.body_z_cmd is not None:
            return False
        if not math.isnan(sp.position_ned_m[2]):
            return sp.position_ned_m[2] > self.est_position_ned_m[2] - 0.2
        if not math.isnan(sp.velocity_ned_m_s[2]):
            return sp.velocity_ned_m_s[2] >= 0.0
        return True

    def _commander(self, t_s: float) -> None:
        landed = self.landed
        # back to Offboard when setpoints resume after an offboard-loss failsafe (PX4: the user's intended mode is
        # still Offboard; it returns even disarmed, as measured)
        if self._offboard_failsafe and self.offboard_setpoint_fresh():
            self._offboard_failsafe = False
            self._say(6, "Offboard signal regained, back to Offboard")
            self._set_mode(FlightMode.OFFBOARD)
        if not self.armed:
            self._landed_since_s = t_s if landed else None
            return
        if not landed:
            self._has_flown = True
            self._landed_since_s = None
        elif self._landed_since_s is None:
            self._landed_since_s = t_s
        # auto-disarm (COM_DISARM_LAND / COM_DISARM_PRFLT)
        if landed:
            t_land = float(self.params["COM_DISARM_LAND"])
            t_pre = float(self.params["COM_DISARM_PRFLT"])
            if self._has_flown and t_land >= 0 and t_s - self._landed_since_s >= t_land:
                self._disarm("Disarmed by auto disarm on land")
                return
            if (
                not self._has_flown
                and t_pre > 0
                and t_s - self._armed_at_s >= t_pre
                and self.mode != FlightMode.TAKEOFF
            ):
                self._disarm("Disarmed by auto preflight disarming")
                return
        if (self.mode == FlightMode.OFFBOARD and t_s - self._offboard_from_takeoff_t_s <= TAKEOFF_RACE_S
                and self._takeoff_reached()):
            # PX4: the navigator's "takeoff complete -> Hold" of (nearly) the same instant overrides the request
            self._offboard_from_takeoff_t_s = -math.inf
            self._say(6, "Takeoff complete")
            self._set_mode(FlightMode.HOLD)
            self._hold_target = self._takeoff_target.copy()
        # offboard loss failsafe (COM_OF_LOSS_T, then COM_OBL_RC_ACT)
        if self.mode == FlightMode.OFFBOARD and not self.offboard_setpoint_fresh():
            self._offboard_loss_failsafe(landed)
            if not self.armed:
                return
        # battery failsafe: warn at BAT_LOW_THR, return (or land without home) at BAT_CRIT_THR
        low = float(self.params["BAT_LOW_THR"]) * 100.0
        if not self._battery_low_warned and low > 0 and self.battery.remaining_pct <= low:
            self._battery_low_warned = True
            self._say(4, f"Low battery: {self.battery.remaining_pct:.0f}% remaining")
        if not self._battery_failsafe_done and self._battery_critical() and not landed:
            self._battery_failsafe_done = True
            self._offboard_failsafe = False
            self._say(2, "Failsafe: battery critical, returning")
            if self.home_ned_m is not None:
                self._set_mode(FlightMode.RETURN)
            else:
                self._set_mode(FlightMode.LAND)

    def _offboard_loss_failsafe(self, landed: bool) -> None:
        """COM_OBL_RC_ACT: 0..2 (Position/Altitude/Stabilized: need RC, which this simulator never has, so PX4
        falls back to Return) and 3 Return, 4 Land, 5 Hold, 6 Terminate / 7 Disarm (motors off)."""
        act = int(self.params["COM_OBL_RC_ACT"])
        if act in (OBL_TERMINATE, OBL_DISARM):
            self._say(2, "Failsafe: no offboard signal, " + ("terminating" if act == OBL_TERMINATE else "disarming"))
            self._disarm("Disarmed by failsafe")
            return
        if act == OBL_HOLD:
            mode, what = FlightMode.HOLD, "holding"
        elif act == OBL_LAND or landed or self.home_ned_m is None:
            mode, what = FlightMode.LAND, "landing"
        else:  # 0..3 and unknown values: Return, as PX4 without RC
            mode, what = FlightMode.RETURN, "returning"
        self._say(4, f"Failsafe: no offboard signal, {what}")
        self._set_mode(mode)
        self._offboard_failsafe = True

    def _takeoff_reached(self) -> bool:
        """PX4's navigator: takeoff complete once within NAV_MC_ALT_RAD below the takeoff altitude."""
        tgt = self._takeoff_target
        return tgt is not None and self.est_position_ned_m[2] <= tgt[2] + float(self.params["NAV_MC_ALT_RAD"])

    def _auto(self, target: np.ndarray, max_speed_xy_m_s: float = math.nan,
              max_speed_up_m_s: float = math.nan) -> TrajectorySetpoint:
        """The auto modes' smoothed setpoint towards ``target`` (world NED) within PX4's auto limits."""
        P, lim = self.params, self.ctrl.limits
        vxy = float(P["MPC_XY_CRUISE"]) if math.isnan(max_speed_xy_m_s) else max_speed_xy_m_s
        vup = lim.max_speed_up_m_s if math.isnan(max_speed_up_m_s) else max_speed_up_m_s
        sp = self.traj.step(self._dt_s, target, min(vxy, lim.max_speed_xy_m_s), vup,
                            float(P["MPC_Z_V_AUTO_DN"]), float(P["MPC_ACC_HOR"]), lim.max_accel_z_m_s2)
        sp.yaw_rad = self._hold_yaw_or_current()
        return sp

    def _land_speed_m_s(self, p: np.ndarray) -> float:
        """PX4's land descent rate: MPC_Z_V_AUTO_DN above MPC_LAND_ALT1, MPC_LAND_SPEED below MPC_LAND_ALT2,
        linear in between (heights above home)."""
        P = self.params
        h = (self.home_ned_m[2] if self.home_ned_m is not None else 0.0) - p[2]
        v_fast, v_slow = float(P["MPC_Z_V_AUTO_DN"]), float(P["MPC_LAND_SPEED"])
        a1, a2 = float(P["MPC_LAND_ALT1"]), float(P["MPC_LAND_ALT2"])
        if h >= a1 or a1 <= a2:
            return v_fast if h >= a1 else v_slow
        if h <= a2:
            return v_slow
        return v_slow + (v_fast - v_slow) * (h - a2) / (a1 - a2)

    def _land_setpoint(self, xy: np.ndarray) -> TrajectorySetpoint:
        p = self.est_position_ned_m
        sp = self._auto(np.array([xy[0], xy[1], p[2]]))
        sp.position_ned_m[2] = np.nan
        sp.velocity_ned_m_s[2] = self._land_speed_m_s(p)
        sp.accel_ned_m_s2[2] = np.nan
        self.traj.position_ned_m[2], self.traj.velocity_ned_m_s[2] = p[2], sp.velocity_ned_m_s[2]
        return sp

    def _mode_setpoint(self) -> TrajectorySetpoint:
        p = self.est_position_ned_m
        P = self.params
        if not self.armed:
            return TrajectorySetpoint()
        m = self.mode
        if m == FlightMode.OFFBOARD and self._offboard_sp is not None:
            return self._offboard_sp  # straight to the position controller, as PX4 offboard
        if m == FlightMode.TAKEOFF and self._takeoff_target is not None:
            tgt = self._takeoff_target
            if self._takeoff_reached():
                self._say(6, "Takeoff complete")
                self._set_mode(FlightMode.HOLD)
                self._hold_target = tgt.copy()  # Hold goes on to the takeoff altitude
                return self._mode_setpoint()
            return self._auto(tgt, max_speed_up_m_s=float(P["MPC_TKO_SPEED"]))
        if m == FlightMode.LAND:
            return self._land_setpoint(self._land_xy if self._land_xy is not None else p[:2])
        if m == FlightMode.RETURN and self.home_ned_m is not None:
            home = self.home_ned_m
            if self._rtl_phase == "climb":
                if p[2] <= self._rtl_alt_d + 0.3:
                    self._rtl_phase = "return"
                else:
                    return self._auto(np.array([self.traj.position_ned_m[0], self.traj.position_ned_m[1],
                                                self._rtl_alt_d]))
            if self._rtl_phase == "return":
                if math.hypot(p[0] - home[0], p[1] - home[1]) < 0.5:
                    self._rtl_phase = "descend"
                else:
                    return self._auto(np.array([home[0], home[1], self._rtl_alt_d]))
            if self._rtl_phase == "descend":
                if p[2] >= self._rtl_descend_d - 0.3:
                    self._rtl_phase = "land"
                else:
                    return self._auto(np.array([home[0], home[1], self._rtl_descend_d]))
            return self._land_setpoint(home[:2])
        # HOLD (and any other mode): hold a point; on the ground stay there
        if self.landed and (self._hold_target is None or self._hold_target[2] >= p[2] - 0.2):
            self.traj.reset(p)
            return TrajectorySetpoint(velocity_ned_m_s=np.array([0.0, 0.0, 0.5]))
        if self._hold_target is None:
            self._hold_target = p.copy()
        return self._auto(self._hold_target, max_speed_xy_m_s=self._hold_speed_m_s)

    def _hold_yaw_or_current(self) -> float:
        if math.isnan(self._hold_yaw):
            self._hold_yaw = self.est_yaw_rad
        return self._hold_yaw
