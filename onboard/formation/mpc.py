"""Decentralised formation MPC: each drone plans its own trajectory around the predicted person.

Problem solved every control step by drone ``i`` (horizon ``N`` steps of ``dt``; double integrator,
state ``x = [p (3), v (3)]`` NED, input ``u = a (3)``)::

    min  sum_k |p_k - r_k|^2_Wp + w_v |v_k - rv_k|^2 + w_u |u_k|^2 + w_du |u_k - u_{k-1}|^2   (+ terminal x w_N)
    s.t. p_{k+1} = p_k + v_k dt + u_k dt^2 / 2,  v_{k+1} = v_k + u_k dt                     (exact ZOH)
         horizontal speed and acceleration in inner polygons of the discs (5 m/s, a_max_h)
         |v_down| <= v_max_down, |a_down| <= a_max_down, altitude band (hard bounds)
         n_jk . p_k >= h_jk   for every half-space j and step k, from
            - teammates (buffered Voronoi cells): the bisecting plane between my previous plan and the
              teammate's shared plan at step k, shifted by d_min / 2 — if every drone keeps to its side of
              the same planes, their new plans stay >= d_min apart (Zhou et al., RA-L 2017);
            - the person (keep-out radius), static obstacles (vertical cylinders): the tangent plane about
              the previous plan (conservative linearisation of the non-convex keep-out);
            - the geofence polygon (convex, linear).

``r_k`` is this drone's slot: the predicted person (Ornstein-Uhlenbeck velocity decay, as the filter) plus
``radius_m`` at an angle that moves from the drone's current bearing toward its assigned slot angle at
``slot_approach_speed_m_s`` along the circle (so a drone on the far side flies around the person, not into
the keep-out's local minimum), at ``altitude_m`` above ``ground_down_m``. Yaw (and gimbal pitch) toward
the person are computed analytically from the plan. Every constraint is linear and the cost quadratic, so
the problem is a QP with fixed sparsity: built once with CasADi, solved by OSQP (default; warm-started from
the shifted previous plan) or qpOASES / IPOPT for comparison (``bench/bench_tracking.py``).

A constraint that the current state already violates (e.g. drones started too close) is relaxed at each
step by what the drone can recover by then at full acceleration, so the plan moves back to the safe side
as fast as the limits allow instead of being infeasible; likewise a drone already faster than the speed
limits (a vehicle overshoots its setpoint: e.g. still climbing at take-off speed) may slow down at full
deceleration instead of meeting them at the first step. If the solver fails (infeasible: e.g. too fast to
stop before the geofence) or answers later than ``max_solve_time_s``, the controller falls back to "brake
and hold" (full deceleration, then hover) and counts it (:attr:`FormationMPC.fallback_count`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
import zlib
from typing import Literal

import casadi as ca
import numpy as np

from skycap.errors import SkycapError

__all__ = [
    "MpcConfig",
    "Cylinder",
    "SharedPlan",
    "MpcResult",
    "FormationMPC",
    "MpcError",
    "slot_reference",
    "yaw_to_target_rad",
    "predict_person",
]

log = logging.getLogger(__name__)


class MpcError(SkycapError, ValueError):
    """Bad configuration or input of the formation MPC."""


@dataclasses.dataclass(frozen=True)
class Cylinder:
    """A vertical cylinder obstacle (infinite height), NED horizontal centre and radius in metres."""

    north_m: float
    east_m: float
    radius_m: float


@dataclasses.dataclass(frozen=True)
class MpcConfig:
    horizon_steps: int = 15
    dt_s: float = 0.1
    radius_m: float = 8.0  #: horizontal distance to the person
    altitude_m: float = 8.0  #: height above ground_down_m
    max_speed_h_m_s: float = 5.0
    max_speed_down_m_s: float = 1.0
    max_accel_h_m_s2: float = 4.0
    max_accel_down_m_s2: float = 2.0
    min_altitude_m: float = 3.0
    max_altitude_m: float = 30.0
    min_separation_m: float = 3.0
    person_keepout_m: float = 4.0  #: never closer than this (horizontally) to the predicted person
    obstacle_margin_m: float = 1.0
    geofence_margin_m: float = 1.0
    geofence_ne_m: tuple[tuple[float, float], ...] = ()  #: convex polygon vertices (north, east), any order sense
    obstacles: tuple[Cylinder, ...] = ()
    max_teammates: int = 7  #: problem size is fixed at build time
    polygon_sides: int = 12  #: inner polygon approximating the horizontal speed/acceleration discs
    w_position_h: float = 1.0
    w_position_down: float = 4.0
    w_velocity: float = 0.2
    w_accel: float = 0.05
    w_jerk: float = 0.2
    w_terminal: float = 5.0
    person_velocity_tau_s: float = 3.0
    slot_approach_speed_m_s: float = 4.0  #: speed of the reference along the circle toward the slot
    solver: Literal["osqp", "qpoases", "ipopt"] = "osqp"
    separation: Literal["bvc", "nonconvex"] = "bvc"  #: "nonconvex": hard |p_k - q_jk| >= d_min (IPOPT only)
    max_solve_time_s: float = 0.05  #: later than this -> fallback (the result is not used)
    max_iter: int = 4000
    solver_margin_m: float = 0.03  #: added to separation and keep-outs: first-order solvers stop at ~1e-3..1e-2

    def __post_init__(self):
        if self.horizon_steps < 2 or not self.dt_s > 0:
            raise MpcError(f"MpcConfig: horizon_steps >= 2 and dt_s > 0 needed, got {self.horizon_steps}, {self.dt_s}")
        if not self.min_altitude_m < self.max_altitude_m:
            raise MpcError("MpcConfig: min_altitude_m must be below max_altitude_m")
        if not self.min_altitude_m <= self.altitude_m <= self.max_altitude_m:
            raise MpcError(f"MpcConfig: altitude_m {self.altitude_m} outside the band [{self.min_altitude_m}, {self.max_altitude_m}]")
        if self.polygon_sides < 6 or self.polygon_sides % 2:
            raise MpcError("MpcConfig: polygon_sides must be even and >= 6")
        if self.separation == "nonconvex" and self.solver != "ipopt":
            raise MpcError("MpcConfig: separation='nonconvex' needs solver='ipopt' (a QP solver takes linear constraints only)")
        if self.geofence_ne_m and len(self.geofence_ne_m) < 3:
            raise MpcError("MpcConfig: a geofence needs at least 3 vertices (north_m, east_m)")


@dataclasses.dataclass(frozen=True)
class SharedPlan:
    """A drone's planned positions, shared with its teammates.

    t0_ns: time of positions_ned_m[0]; dt_s: step; positions_ned_m: (N + 1, 3)."""

    drone_id: str
    t0_ns: int
    dt_s: float
    positions_ned_m: np.ndarray

    @classmethod
    def from_state(cls, drone_id: str, t_ns: int, position_ned_m, velocity_ned_m_s, dt_s: float, horizon_steps: int) -> "SharedPlan":
        """A constant-velocity plan from a teammate's reported state, for a teammate whose plan has not
        arrived (yet): without any plan a teammate is not avoided at all."""
        k = np.arange(horizon_steps + 1)[:, None] * dt_s
        pos = np.asarray(position_ned_m, dtype=float) + k * np.asarray(velocity_ned_m_s, dtype=float)
        return cls(drone_id, int(t_ns), dt_s, pos)

    def sample(self, t_ns: np.ndarray) -> np.ndarray:
        """Positions at times t_ns (M,) -> (M, 3), linear interpolation, held constant outside the plan."""
        ts = self.t0_ns + np.arange(len(self.positions_ned_m)) * self.dt_s * 1e9
        t = np.asarray(t_ns, dtype=float)
        return np.stack([np.interp(t, ts, self.positions_ned_m[:, i]) for i in range(3)], axis=1)


@dataclasses.dataclass(frozen=True)
class MpcResult:
    """One control step's output.

    setpoint_*: the state the drone should be at one step ahead (position (3,), velocity (3,), yaw rad);
    plan: the shared plan (N + 1 positions from now); plan_velocities_ned_m_s (N + 1, 3); plan_yaw_rad
    (N + 1,) and plan_gimbal_pitch_rad (N + 1,) toward the predicted person.
    """

    ok: bool
    fallback: bool
    status: str
    solve_time_s: float
    setpoint_position_ned_m: np.ndarray
    setpoint_velocity_ned_m_s: np.ndarray
    setpoint_yaw_rad: float
    plan: SharedPlan
    plan_velocities_ned_m_s: np.ndarray
    plan_yaw_rad: np.ndarray
    plan_gimbal_pitch_rad: np.ndarray
    min_teammate_distance_m: float  #: over the plan, to the teammates' plans (inf without teammates)
    min_geofence_margin_m: float  #: over the plan, distance inside the geofence polygon (inf without one)
    reference_ned_m: np.ndarray  #: (N, 3) the slot points used


def predict_person(position_ned_m, velocity_ned_m_s, t_s: np.ndarray, tau_s: float) -> np.ndarray:
    """Person positions at times t_s (K,) with the filter's decaying velocity: p + v tau (1 - exp(-t / tau))."""
    t = np.asarray(t_s, dtype=float)[:, None]
    return np.asarray(position_ned_m, float) + np.asarray(velocity_ned_m_s, float) * tau_s * (1.0 - np.exp(-t / tau_s))


def slot_reference(person_ned_m: np.ndarray, angle_rad: float, radius_m: float, altitude_m: float, ground_down_m: float) -> np.ndarray:
    """Slot positions (K, 3) for person positions (K, 3): radius at angle (from north toward east), altitude above ground."""
    p = np.atleast_2d(np.asarray(person_ned_m, dtype=float))
    out = p.copy()
    out[:, 0] += radius_m * math.cos(angle_rad)
    out[:, 1] += radius_m * math.sin(angle_rad)
    out[:, 2] = ground_down_m - altitude_m
    return out


def yaw_to_target_rad(positions_ned_m: np.ndarray, target_ned_m: np.ndarray) -> np.ndarray:
    """Yaw (0 = north, + toward east) from positions (K, 3) toward targets (K, 3)."""
    d = np.atleast_2d(target_ned_m) - np.atleast_2d(positions_ned_m)
    return np.arctan2(d[:, 1], d[:, 0])


def _gimbal_pitch_rad(positions, targets) -> np.ndarray:
    d = np.atleast_2d(targets) - np.atleast_2d(positions)
    return -np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))


def _reach(t_s: np.ndarray, v0_toward: float, v_max: float, a_max: float, safety: float = 0.8) -> np.ndarray:
    """Displacement (K,) surely reachable toward a direction by times t_s, starting at speed v0_toward
    (negative = moving away), accelerating at a_max up to v_max; scaled by ``safety`` and never < 0."""
    t = np.asarray(t_s, dtype=float)
    v0 = min(float(v0_toward), v_max)
    t1 = (v_max - v0) / a_max
    d = np.where(t <= t1, v0 * t + 0.5 * a_max * t**2, v0 * t1 + 0.5 * a_max * t1**2 + v_max * (t - t1))
    return np.maximum(safety * d, 0.0) if v0 >= 0 else np.maximum(d - (1 - safety) * np.abs(d), 0.0)


class FormationMPC:
    """The formation MPC of one drone; build once (CasADi), call :meth:`step` every ``dt_s``."""

    def __init__(self, drone_id: str, config: MpcConfig = MpcConfig()):
        self.drone_id = drone_id
        self.cfg = config
        self.fallback_count = 0
        self.solve_count = 0
        self.last_status = "not run"
        c = config
        self.N = c.horizon_steps
        fence = self._fence_halfspaces(c.geofence_ne_m, c.geofence_margin_m + c.solver_margin_m)
        self._fence = fence  # (E, 2) normals (pointing inside), (E,) offsets: n . p_ne >= h
        self.L = c.max_teammates + 1 + len(c.obstacles) + len(fence[1])
        self._build()
        self._prev_w: np.ndarray | None = None
        self._prev_lam_g: np.ndarray | None = None
        self._prev_lam_x: np.ndarray | None = None
        self._prev_plan: np.ndarray | None = None  # (N + 1, 3) positions
        self._prev_t_ns: int | None = None

    # ------------------------------------------------------------------ build
    @staticmethod
    def _fence_halfspaces(verts, margin):
        if not verts:
            return np.zeros((0, 2)), np.zeros(0)
        V = np.asarray(verts, dtype=float)
        centroid = V.mean(axis=0)
        normals, offsets = [], []
        for i in range(len(V)):
            a, b = V[i], V[(i + 1) % len(V)]
            e = b - a
            n = np.array([-e[1], e[0]]) / np.linalg.norm(e)
            if n @ (centroid - a) < 0:
                n = -n
            normals.append(n)
            offsets.append(n @ a + margin)
        normals, offsets = np.array(normals), np.array(offsets)
        if np.any(normals @ V.T - offsets[:, None] < -margin - 1e-9):
            raise MpcError("MpcConfig.geofence_ne_m must be a convex polygon (vertices in order)")
        return normals, offsets

    def _build(self) -> None:
        c, N, L = self.cfg, self.N, self.L
        dt = c.dt_s
        nx, nu = 6, 3
        U = ca.SX.sym("u", nu, N)
        X = ca.SX.sym("x", nx, N)  # x_1 .. x_N
        x0 = ca.SX.sym("x0", nx)
        ref_p = ca.SX.sym("ref_p", 3, N)
        ref_v = ca.SX.sym("ref_v", 3, N)
        u_prev = ca.SX.sym("u_prev", nu)
        hs_n = ca.SX.sym("hs_n", 3, L * N)  # half-space normals per (row, step)
        M = c.max_teammates if c.separation == "nonconvex" else 0
        mates = ca.SX.sym("mates", 3, M * N)  # teammates' planned positions (nonconvex variant)
        w_list, g = [], []
        f = 0
        xk = x0
        uk_prev = u_prev
        Wp = ca.diag(ca.DM([c.w_position_h, c.w_position_h, c.w_position_down]))
        sides = c.polygon_sides // 2
        dirs = [(math.cos(math.pi * s / sides), math.sin(math.pi * s / sides)) for s in range(sides)]
        self._polygon_dirs = np.array(dirs)  # (sides, 2): the rows of the horizontal speed / acceleration polygons
        for k in range(N):
            uk = U[:, k]
            xn = X[:, k]
            w_list += [uk, xn]
            p, v = xk[:3], xk[3:]
            g.append(xn[:3] - (p + v * dt + 0.5 * uk * dt**2))
            g.append(xn[3:] - (v + uk * dt))
            for cs, sn in dirs:  # horizontal speed and acceleration polygons
                g.append(cs * xn[3] + sn * xn[4])
                g.append(cs * uk[0] + sn * uk[1])
            for j in range(L):
                g.append(ca.dot(hs_n[:, j * N + k], xn[:3]))
            for j in range(M):
                g.append(ca.sumsqr(xn[:3] - mates[:, j * N + k]))
            wk = c.w_terminal if k == N - 1 else 1.0
            ep = xn[:3] - ref_p[:, k]
            ev = xn[3:] - ref_v[:, k]
            f += wk * (ca.mtimes([ep.T, Wp, ep]) + c.w_velocity * ca.sumsqr(ev))
            f += c.w_accel * ca.sumsqr(uk) + c.w_jerk * ca.sumsqr(uk - uk_prev)
            xk = xn
            uk_prev = uk
        w = ca.vertcat(*w_list)
        g = ca.vertcat(*g)
        P = ca.vertcat(x0, ca.vec(ref_p), ca.vec(ref_v), u_prev, ca.vec(hs_n), ca.vec(mates))
        self._n_w, self._n_g, self._n_p = w.numel(), g.numel(), P.numel()
        self._M = M
        self._rows_per_step = 6 + 2 * sides + L + M
        prob = {"x": w, "p": P, "f": f, "g": g}
        if c.solver == "osqp":
            opts = {
                "osqp": {"verbose": False, "eps_abs": 1e-4, "eps_rel": 1e-4, "max_iter": c.max_iter, "polishing": True},
                "warm_start_primal": True,
                "warm_start_dual": True,
                "error_on_fail": False,
            }
            self._solver = ca.qpsol("formation_mpc", "osqp", prob, opts)
        elif c.solver == "qpoases":
            opts = {"printLevel": "none", "error_on_fail": False, "sparse": False, "nWSR": c.max_iter, "CPUtime": c.max_solve_time_s}
            self._solver = ca.qpsol("formation_mpc", "qpoases", prob, opts)
        elif c.solver == "ipopt":
            opts = {
                "ipopt": {"print_level": 0, "max_cpu_time": c.max_solve_time_s, "tol": 1e-6, "warm_start_init_point": "yes", "max_iter": c.max_iter},
                "print_time": False,
                "error_on_fail": False,
            }
            self._solver = ca.nlpsol("formation_mpc", "ipopt", prob, opts)
        else:
            raise MpcError(f"unknown MPC solver {c.solver!r}; use 'osqp', 'qpoases' or 'ipopt'")
        # constant bounds on w (vertical speed/accel) and g (dynamics, polygons)
        lbw, ubw = [], []
        big = 1e9
        for k in range(N):
            lbw += [-big, -big, -c.max_accel_down_m_s2] + [-big, -big, -big, -big, -big, -c.max_speed_down_m_s]
            ubw += [big, big, c.max_accel_down_m_s2] + [big, big, big, big, big, c.max_speed_down_m_s]
        self._lbw0, self._ubw0 = np.array(lbw), np.array(ubw)
        # inner-polygon bounds of the horizontal speed and acceleration discs
        self._vpol = vpol = c.max_speed_h_m_s * math.cos(math.pi / c.polygon_sides)
        self._apol = apol = c.max_accel_h_m_s2 * math.cos(math.pi / c.polygon_sides)
        lbg_step = [0.0] * 6 + [-vpol, -apol] * sides + [-np.inf] * (L + M)
        ubg_step = [0.0] * 6 + [vpol, apol] * sides + [np.inf] * (L + M)
        self._lbg0 = np.tile(lbg_step, N)
        self._ubg0 = np.tile(ubg_step, N)

    # ------------------------------------------------------------------ helpers
    def _relax_speed_limits(self, v0: np.ndarray, t_steps_s: np.ndarray, lbw, ubw, lbg, ubg) -> None:
        """Widen the speed limits (in place) for a drone that is already faster than them.

        A real vehicle overshoots its velocity setpoint (e.g. still climbing at take-off speed when the
        formation starts, or a gust): a hard |v_k| <= v_max from the first step on is then infeasible, and
        the controller would brake and hold. Instead, at step k the limit is what braking at full
        acceleration reaches by then. Vertical: max(v_max, |v_down,0| - a_max t_k). Horizontal (every row
        d of the speed polygon): max(v_pol, |d . v0| (1 - a_pol t_k / |v0_h|)), the speed of a braking
        straight against v0_h at a_pol, which satisfies every row of the acceleration polygon. A drone
        within the limits gets the plain limits."""
        c, N = self.cfg, self.N
        brake = 0.98  # plan slightly softer than the limit: the relaxed bound is never the binding one
        vz = float(v0[2])
        if abs(vz) > c.max_speed_down_m_s:
            lim = np.maximum(c.max_speed_down_m_s, abs(vz) - brake * c.max_accel_down_m_s2 * t_steps_s)
            i = np.arange(N) * 9 + 8  # v_down of x_{k+1}
            if vz > 0:
                ubw[i] = lim
            else:
                lbw[i] = -lim
        vh = float(np.hypot(v0[0], v0[1]))
        if vh <= 1e-9:
            return
        proj = np.abs(self._polygon_dirs @ v0[:2])  # (sides,)
        if not np.any(proj > self._vpol):
            return
        shrink = np.maximum(0.0, 1.0 - brake * self._apol * t_steps_s / vh)  # (N,)
        lim = np.maximum(self._vpol, shrink[:, None] * proj[None, :])  # (N, sides)
        rows = np.arange(N)[:, None] * self._rows_per_step + 6 + 2 * np.arange(len(proj))[None, :]  # speed rows
        lbg[rows] = -lim
        ubg[rows] = lim

    def _idx_pos(self, k: int) -> slice:
        """w indices of p_{k+1} (k = 0 .. N-1)."""
        base = k * 9 + 3
        return slice(base, base + 3)

    def _unpack(self, w: np.ndarray, x0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        W = w.reshape(self.N, 9)
        U, X = W[:, :3], W[:, 3:]
        states = np.vstack([x0, X])
        return states[:, :3], states[:, 3:], U

    def _brake_plan(self, p0: np.ndarray, v0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Full deceleration to hover, then hold: positions and velocities (N + 1, 3)."""
        c = self.cfg
        P = np.zeros((self.N + 1, 3))
        V = np.zeros((self.N + 1, 3))
        P[0], V[0] = p0, v0
        for k in range(self.N):
            v = V[k]
            a = np.zeros(3)
            vh = v[:2]
            sh = np.linalg.norm(vh)
            if sh > 1e-9:
                a[:2] = -vh / sh * min(c.max_accel_h_m_s2, sh / c.dt_s)
            a[2] = -np.sign(v[2]) * min(c.max_accel_down_m_s2, abs(v[2]) / c.dt_s)
            V[k + 1] = v + a * c.dt_s
            P[k + 1] = P[k] + v * c.dt_s + 0.5 * a * c.dt_s**2
        return P, V

    # ------------------------------------------------------------------ step
    def step(
        self,
        t_ns: int,
        position_ned_m: np.ndarray,
        velocity_ned_m_s: np.ndarray,
        person_position_ned_m: np.ndarray,
        person_velocity_ned_m_s: np.ndarray,
        slot_angle_rad: float,
        teammate_plans: dict[str, SharedPlan] | None = None,
        ground_down_m: float = 0.0,
    ) -> MpcResult:
        """One control step at time t_ns from this drone's state (position (3,), velocity (3,)), the predicted
        person (position (3,), velocity (3,)), its slot angle and the teammates' latest shared plans."""
        c, N, L = self.cfg, self.N, self.L
        p0 = np.asarray(position_ned_m, dtype=float).reshape(3)
        v0 = np.asarray(velocity_ned_m_s, dtype=float).reshape(3)
        pp = np.asarray(person_position_ned_m, dtype=float).reshape(3)
        pv = np.asarray(person_velocity_ned_m_s, dtype=float).reshape(3)
        for name, arr in (("position", p0), ("velocity", v0), ("person position", pp), ("person velocity", pv)):
            if not np.all(np.isfinite(arr)):
                raise MpcError(f"FormationMPC.step: {name} is not finite ({arr}); hold position instead of planning")
        if not math.isfinite(slot_angle_rad):
            raise MpcError("FormationMPC.step: slot_angle_rad is not finite")
        teammate_plans = {k: v for k, v in (teammate_plans or {}).items() if k != self.drone_id}
        if len(teammate_plans) > c.max_teammates:
            raise MpcError(f"{len(teammate_plans)} teammates exceed MpcConfig.max_teammates={c.max_teammates}; raise it")
        t_steps_s = (np.arange(1, N + 1)) * c.dt_s
        t_steps_ns = t_ns + (t_steps_s * 1e9).astype(np.int64)
        person_k = predict_person(pp, pv, t_steps_s, c.person_velocity_tau_s)
        person_vel_k = pv * np.exp(-t_steps_s / c.person_velocity_tau_s)[:, None]
        # the reference walks along the circle from the drone's current bearing to its slot (at most
        # slot_angular_speed), so a drone on the far side goes around the person instead of at it
        phi0 = math.atan2(p0[1] - pp[1], p0[0] - pp[0])
        delta = (slot_angle_rad - phi0 + math.pi) % (2 * math.pi) - math.pi
        omega = c.slot_approach_speed_m_s / c.radius_m
        ang_k = phi0 + np.sign(delta) * np.minimum(abs(delta), omega * t_steps_s)
        ref_p = person_k.copy()
        ref_p[:, 0] += c.radius_m * np.cos(ang_k)
        ref_p[:, 1] += c.radius_m * np.sin(ang_k)
        ref_p[:, 2] = ground_down_m - c.altitude_m
        ref_v = person_vel_k.copy()
        ref_v[:, 2] = 0.0

        # previous plan (linearisation point), shifted to the current time
        if self._prev_plan is not None and self._prev_t_ns is not None:
            mine = SharedPlan(self.drone_id, self._prev_t_ns, c.dt_s, self._prev_plan)
            # teammates' planes use exactly the plan they received from me (the same pair of plans on both
            # sides is what makes the buffered Voronoi cells disjoint)
            prev_shared = mine.sample(t_steps_ns.astype(float))
            # the keep-outs linearise about the plan anchored on where I really am now
            prev = prev_shared + (p0 - mine.sample(np.array([float(t_ns)]))[0])
        else:
            prev = p0 + v0 * t_steps_s[:, None]
            prev_shared = prev

        # half-spaces n . p_k >= h_k, shape (L, N, 3) and (L, N)
        hn = np.zeros((L, N, 3))
        hh = np.full((L, N), -np.inf)
        row = 0
        min_dist = np.inf
        mates_q = np.zeros((max(self._M, 0), N, 3))
        mates_lb = np.full((max(self._M, 0), N), -np.inf)
        for m_i, tid in enumerate(sorted(teammate_plans)):
            q = teammate_plans[tid].sample(t_steps_ns.astype(float))
            if self._M:
                mates_q[m_i] = q
                mates_lb[m_i] = c.min_separation_m**2
                continue
            d = prev_shared - q
            dist = np.linalg.norm(d, axis=1)
            n = np.empty_like(d)
            ok = dist > 1e-3
            n[ok] = d[ok] / dist[ok, None]
            if not np.all(ok):
                # coincident: a direction both drones agree on (from the pair's names), opposite signs
                a, b = sorted([self.drone_id, tid])
                ang = (zlib.crc32(f"{a}|{b}".encode()) % 3600) * math.pi / 1800
                sgn = 1.0 if self.drone_id == a else -1.0
                n[~ok] = sgn * np.array([math.cos(ang), math.sin(ang), 0.0])
            hn[row] = n
            # old plans closer than d_min (first step, after a fallback, a teammate's from_state plan): ask
            # only for the separation that can be regained by step k (keeps the problem feasible; the pair
            # computes the same offsets); old plans >= d_min apart give the plain buffered Voronoi cells
            regain = _reach(t_steps_s, 0.0, c.max_speed_h_m_s, c.max_accel_h_m_s2)
            off = 0.5 * np.minimum(c.min_separation_m + c.solver_margin_m, dist + regain)
            hh[row] = np.einsum("ij,ij->i", n, 0.5 * (prev_shared + q)) + off
            row += 1
        row = c.max_teammates
        # the person keep-out (horizontal tangent plane about the previous plan)
        slot_dir = np.array([math.cos(slot_angle_rad), math.sin(slot_angle_rad)])
        dpn = prev[:, :2] - person_k[:, :2]
        dn = np.linalg.norm(dpn, axis=1)
        n2 = np.where(dn[:, None] < 1e-3, slot_dir, dpn / np.maximum(dn, 1e-3)[:, None])  # right above: leave toward the slot
        hn[row, :, :2] = n2
        hh[row] = np.einsum("ij,ij->i", n2, person_k[:, :2]) + c.person_keepout_m + c.solver_margin_m
        row += 1
        for ob in c.obstacles:
            cen = np.array([ob.north_m, ob.east_m])
            d2 = prev[:, :2] - cen
            dd = np.linalg.norm(d2, axis=1)
            n2 = np.where(dd[:, None] < 1e-3, slot_dir, d2 / np.maximum(dd, 1e-3)[:, None])
            hn[row, :, :2] = n2
            hh[row] = n2 @ cen + ob.radius_m + c.obstacle_margin_m + c.solver_margin_m
            row += 1
        fn, fh = self._fence
        for e in range(len(fh)):
            hn[row, :, :2] = fn[e]
            hh[row] = fh[e]
            row += 1
        # relax rows the current state already violates by what can be recovered by step k
        viol0 = hh - np.einsum("lkj,j->lk", hn, p0)
        v_toward = np.einsum("lkj,j->l", hn[:, :1], v0)  # speed toward the safe side, per row
        recover = np.stack([_reach(t_steps_s, vt, c.max_speed_h_m_s, c.max_accel_h_m_s2) for vt in v_toward])
        relax = np.where(viol0[:, :1] > 0, np.maximum(0.0, viol0[:, :1] - recover), 0.0)
        hh_eff = np.where(np.isfinite(hh), hh - relax, hh)

        # bounds
        lbw, ubw = self._lbw0.copy(), self._ubw0.copy()
        lo_d, hi_d = ground_down_m - c.max_altitude_m, ground_down_m - c.min_altitude_m
        up_rec = _reach(t_steps_s, -v0[2], c.max_speed_down_m_s, c.max_accel_down_m_s2)  # climb possible by t
        down_rec = _reach(t_steps_s, v0[2], c.max_speed_down_m_s, c.max_accel_down_m_s2)
        for k in range(N):
            i = self._idx_pos(k).start + 2
            lbw[i] = min(lo_d, p0[2] + down_rec[k]) if p0[2] < lo_d else lo_d
            ubw[i] = max(hi_d, p0[2] - up_rec[k]) if p0[2] > hi_d else hi_d
        lbg, ubg = self._lbg0.copy(), self._ubg0.copy()
        rps = self._rows_per_step
        M = self._M
        self._relax_speed_limits(v0, t_steps_s, lbw, ubw, lbg, ubg)
        for k in range(N):
            lbg[k * rps + rps - L - M : k * rps + rps - M] = hh_eff[:, k]
            if M:
                lbg[k * rps + rps - M : (k + 1) * rps] = mates_lb[:, k]
        u_prev = np.zeros(3)
        if self._prev_w is not None:
            u_prev = self._prev_w[:3]
        # CasADi vec() is column-major: ref_p (3, N) -> step by step; hs_n (3, L*N) column j*N + k = row j, step k
        P = np.concatenate([p0, v0, ref_p.reshape(-1), ref_v.reshape(-1), u_prev, hn.reshape(L * N, 3).reshape(-1), mates_q.reshape(-1)])
        w0 = self._warm_start(p0, v0)
        args = dict(x0=w0, p=P, lbx=lbw, ubx=ubw, lbg=lbg, ubg=ubg)
        if self._prev_lam_g is not None:
            args["lam_g0"] = self._prev_lam_g
            args["lam_x0"] = self._prev_lam_x
        t0 = time.perf_counter()
        sol = self._solver(**args)
        solve_s = time.perf_counter() - t0
        stats = self._solver.stats()
        self.solve_count += 1
        w = np.asarray(sol["x"]).reshape(-1)
        status = str(stats.get("return_status", "?"))
        # OSQP's "solved inaccurate" (iteration limit near the solution) is used when the constraint check
        # below passes; everything else that is not a success falls back
        ok = (bool(stats.get("success", False)) or status == "solved inaccurate") and bool(np.all(np.isfinite(w)))
        if ok:
            # verify hard constraints within tolerance (first-order solvers stop at eps)
            gval = np.asarray(ca.DM(sol["g"])).reshape(-1) if "g" in sol else None
            if gval is not None and (np.any(gval < lbg - 1e-2) or np.any(gval > ubg + 1e-2)):
                ok, status = False, status + " (constraint violation > 1e-2)"
        late = solve_s > c.max_solve_time_s
        if late:
            status = f"late ({solve_s * 1e3:.1f} ms > {c.max_solve_time_s * 1e3:.1f} ms)"
        ref_full = np.vstack([slot_reference(pp, slot_angle_rad, c.radius_m, c.altitude_m, ground_down_m), ref_p])
        person_full = np.vstack([pp, person_k])
        if ok and not late:
            Pp, Vv, _ = self._unpack(w, np.concatenate([p0, v0]))
            self._prev_w = w
            self._prev_lam_g = np.asarray(sol["lam_g"]).reshape(-1)
            self._prev_lam_x = np.asarray(sol["lam_x"]).reshape(-1)
            fallback = False
        else:
            self.fallback_count += 1
            log.warning("%s: formation MPC %s: brake and hold (fallback %d)", self.drone_id, status, self.fallback_count)
            Pp, Vv = self._brake_plan(p0, v0)
            self._prev_w = None
            self._prev_lam_g = self._prev_lam_x = None
            fallback = True
        self.last_status = status
        self._prev_plan = Pp
        self._prev_t_ns = int(t_ns)
        for tid, plan in teammate_plans.items():
            q = plan.sample((t_ns + np.arange(N + 1) * c.dt_s * 1e9).astype(float))
            min_dist = min(min_dist, float(np.min(np.linalg.norm(Pp - q, axis=1))))
        yaw = yaw_to_target_rad(Pp, person_full)
        return MpcResult(
            ok=bool(ok and not late),
            fallback=fallback,
            status=status,
            solve_time_s=solve_s,
            setpoint_position_ned_m=Pp[1].copy(),
            setpoint_velocity_ned_m_s=Vv[1].copy(),
            setpoint_yaw_rad=float(yaw[1]),
            plan=SharedPlan(self.drone_id, int(t_ns), c.dt_s, Pp.copy()),
            plan_velocities_ned_m_s=Vv.copy(),
            plan_yaw_rad=yaw,
            plan_gimbal_pitch_rad=_gimbal_pitch_rad(Pp, person_full),
            min_teammate_distance_m=min_dist,
            min_geofence_margin_m=self.geofence_margin_m(Pp),
            reference_ned_m=ref_full[1:],
        )

    def geofence_margin_m(self, positions_ned_m: np.ndarray) -> float:
        """Smallest distance (m) of positions (K, 3) inside the geofence polygon (negative = outside; inf
        without a fence); for the failsafe's "breach imminent" check."""
        fn, fh = self._fence
        if len(fh) == 0:
            return float("inf")
        d = np.atleast_2d(positions_ned_m)[:, :2] @ fn.T - (fh - self.cfg.geofence_margin_m - self.cfg.solver_margin_m)
        return float(d.min())

    def _warm_start(self, p0: np.ndarray, v0: np.ndarray) -> np.ndarray:
        """The previous solution shifted by one step (last input repeated), or a coasting guess."""
        N = self.N
        if self._prev_w is not None:
            W = self._prev_w.reshape(N, 9)
            W = np.vstack([W[1:], W[-1:]])
            return W.reshape(-1)
        P, V = self._brake_plan(p0, v0)
        W = np.zeros((N, 9))
        W[:, 3:6] = P[1:]
        W[:, 6:9] = V[1:]
        return W.reshape(-1)
